/* Frame timer on Timer1, fast PWM mode 14 (TOP = ICR1).
 *
 * Frame trigger: OC1A is set by the hardware when the counter passes from TOP to 0 (BOTTOM) and
 * cleared at the OCR1A match, so every rising edge is exactly (TOP + 1) * prescaler CPU cycles after
 * the previous one, whatever the software does. Frame n (0-based) begins at the n+1-th BOTTOM after
 * START; `s_frames` counts those (TIMER1_OVF, flag set at TOP on the chip).
 *
 * The trigger output is connected (COM1A) only in the first OCR1A-match interrupt after START, so
 * the first rising edge is the first real BOTTOM, on the chip and in the simulator alike.
 *
 * Pulse channel 0: OC1B, connected only for the frame of the pulse. OCR1B is double-buffered in the
 * PWM modes (the new value takes effect at BOTTOM), so arming in frame n-1 (at its OCR1A match)
 * makes the hardware set OC1B at the start of frame n and clear it width_ticks later. The OCR1B
 * match interrupt of frame n disconnects it again.
 */
#include "frame_timer.h"

#include <avr/interrupt.h>
#include <avr/io.h>

#include "board.h"

#define PULSE_NOW 0xFFFFFFFFu
#define EVQ_SIZE 8 /* power of two */

enum { PULSE_IDLE = 0, PULSE_WAITING, PULSE_ARMED };

static volatile uint32_t s_frames;   /* trigger pulses started since the last STOP_RESET */
static volatile uint8_t s_running;
static volatile uint8_t s_trig_on;   /* OC1A connected (first OCR1A match after START passed) */
static uint8_t s_cs = 2;             /* prescaler code == CS12:0 value */
static uint16_t s_top = 19999;       /* 100 Hz at 16 MHz, /8 */
static uint16_t s_trig_ocr;          /* trigger width - 1, in ticks */

static volatile uint8_t s_pulse_state;
static volatile uint32_t s_pulse_frame;
static volatile uint16_t s_pulse_ocr;

static volatile ft_event_t s_evq[EVQ_SIZE];
static volatile uint8_t s_ev_head, s_ev_tail;
static volatile uint16_t s_ev_dropped;

/* Trigger pulse width: 100 us, at least 2 ticks, at most half a frame. */
static uint16_t trig_width_ticks(uint8_t cs, uint16_t top) {
    static const uint16_t div[6] = {0, 1, 8, 64, 256, 1024};
    uint32_t w = (F_CPU / 10000UL) / div[cs];
    uint32_t half = ((uint32_t)top + 1) / 2;
    if (w < 2)
        w = 2;
    if (w > half)
        w = half;
    return (uint16_t)w;
}

void ft_timer_init(void) {
    TRIG_PORT &= (uint8_t)~_BV(TRIG_BIT);
    TRIG_DDR |= _BV(TRIG_BIT);
    PULSE_PORT &= (uint8_t)~_BV(PULSE_BIT);
    PULSE_DDR |= _BV(PULSE_BIT);
    TCCR1B = 0;
    TCCR1A = _BV(WGM11);
    TCCR1B = _BV(WGM13) | _BV(WGM12);
    s_trig_ocr = trig_width_ticks(s_cs, s_top) - 1;
    /* Event input: pull-up on (an open-collector photodiode board or a button to ground works
     * without parts), interrupt on any edge. */
    EVT_PORT |= _BV(EVT_BIT);
    EICRA = (uint8_t)((EICRA & ~(_BV(ISC01) | _BV(ISC00))) | _BV(ISC00));
    EIFR = _BV(INTF0);
    EIMSK |= _BV(INT0);
}

uint8_t ft_timer_set_rate(uint8_t cs, uint16_t top) {
    static const uint16_t div[6] = {0, 1, 8, 64, 256, 1024};
    if (cs < 1 || cs > 5 || top < FT_MIN_TOP)
        return FT_TIMER_BAD_ARG;
    if (((uint32_t)top + 1) * div[cs] < FT_MIN_PERIOD_CYCLES)
        return FT_TIMER_BAD_ARG;
    if (s_running)
        return FT_TIMER_BUSY;
    s_cs = cs;
    s_top = top;
    s_trig_ocr = trig_width_ticks(cs, top) - 1;
    return FT_TIMER_OK;
}

void ft_timer_get_rate(uint8_t *cs, uint16_t *top) {
    *cs = s_cs;
    *top = s_top;
}

uint8_t ft_timer_running(void) {
    return s_running;
}

void ft_timer_start(void) {
    uint8_t sreg = SREG;
    if (s_running)
        return;
    cli();
    TCCR1B = _BV(WGM13) | _BV(WGM12); /* clock off while configuring */
    TCCR1A = _BV(WGM11);              /* outputs disconnected: the pins follow PORT (low) */
    TRIG_PORT &= (uint8_t)~_BV(TRIG_BIT);
    ICR1 = s_top;
    OCR1A = s_trig_ocr;
    OCR1B = 0;
    TCNT1 = 0;
    TIFR1 = _BV(TOV1) | _BV(OCF1A) | _BV(OCF1B) | _BV(ICF1);
    TIMSK1 = _BV(TOIE1) | _BV(OCIE1A);
    s_trig_on = 0;
    s_running = 1;
    TCCR1B = (uint8_t)(_BV(WGM13) | _BV(WGM12) | s_cs);
    SREG = sreg;
}

void ft_timer_stop(void) {
    uint8_t sreg = SREG;
    cli();
    if (s_running) {
        uint16_t t;
        TCCR1B = _BV(WGM13) | _BV(WGM12);
        t = TCNT1;
        /* A BOTTOM that happened but was not counted yet (flag set, interrupt not yet run). On the
         * chip the flag rises at TOP, one tick before BOTTOM: t == TOP means no pulse began. */
        if ((TIFR1 & _BV(TOV1)) && t != s_top)
            s_frames++;
        TIMSK1 = 0;
        TIFR1 = _BV(TOV1) | _BV(OCF1A) | _BV(OCF1B) | _BV(ICF1);
        TCCR1A = _BV(WGM11); /* disconnect: trigger and pulse pins go to their PORT level */
        TRIG_PORT &= (uint8_t)~_BV(TRIG_BIT);
        s_running = 0;
        s_trig_on = 0;
    }
    s_pulse_state = PULSE_IDLE;
    SREG = sreg;
}

void ft_timer_stop_reset(void) {
    uint8_t sreg = SREG;
    ft_timer_stop();
    cli();
    s_frames = 0;
    SREG = sreg;
}

/* Caller has interrupts disabled. Reads (count, ticks) so that a wrap between the two reads cannot
 * be seen: the overflow flag is read before and after TCNT1 and the sample is retaken if it changed,
 * and a pending (not yet counted) overflow is added. TCNT1 == TOP is retaken too: on the chip the
 * flag (and the count) rises at TOP, one tick before the pulse, which would make that one tick
 * ambiguous. The wait is at most one timer tick. */
static void sample_locked(uint32_t *frames, uint16_t *ticks) {
    if (!s_running) {
        *frames = s_frames;
        *ticks = TCNT1;
        return;
    }
    for (;;) {
        uint8_t p1 = TIFR1 & _BV(TOV1);
        uint16_t t = TCNT1;
        uint8_t p2 = TIFR1 & _BV(TOV1);
        if (p1 == p2 && t != s_top) {
            *frames = s_frames + (p1 ? 1u : 0u);
            *ticks = t;
            return;
        }
    }
}

void ft_timer_clock(uint32_t *frames, uint16_t *ticks) {
    uint8_t sreg = SREG;
    cli();
    sample_locked(frames, ticks);
    SREG = sreg;
}

uint8_t ft_timer_pulse(uint32_t frame, uint16_t width_ticks) {
    uint8_t sreg = SREG, rc = FT_TIMER_OK;
    uint32_t frames, earliest;
    uint16_t t;
    if (width_ticks < 1 || width_ticks > s_top / 2)
        return FT_TIMER_BAD_ARG;
    cli();
    if (!s_running || s_pulse_state != PULSE_IDLE) {
        rc = FT_TIMER_BUSY;
    } else {
        sample_locked(&frames, &t);
        /* The pulse for frame n is armed at the OCR1A match of frame n-1 (the frame under way has
         * index frames-1). If this frame's match is still ahead (with a 2-tick margin for the
         * interrupt), the next frame is reachable, else the one after. */
        earliest = frames;
        if ((uint32_t)t + 2 > s_trig_ocr || (TIFR1 & _BV(OCF1A)))
            earliest = frames + 1;
        if (frame == PULSE_NOW)
            frame = earliest;
        if (frame < earliest) {
            rc = FT_TIMER_BAD_ARG;
        } else {
            s_pulse_frame = frame;
            s_pulse_ocr = width_ticks - 1;
            s_pulse_state = PULSE_WAITING;
        }
    }
    SREG = sreg;
    return rc;
}

uint8_t ft_timer_pop_event(ft_event_t *ev) {
    uint8_t sreg = SREG, ok = 0;
    cli();
    if (s_ev_tail != s_ev_head) {
        const volatile ft_event_t *e = &s_evq[s_ev_tail];
        ev->channel = e->channel;
        ev->edge = e->edge;
        ev->frame_count = e->frame_count;
        ev->ticks = e->ticks;
        s_ev_tail = (uint8_t)((s_ev_tail + 1) & (EVQ_SIZE - 1));
        ok = 1;
    }
    SREG = sreg;
    return ok;
}

uint16_t ft_timer_events_dropped(void) {
    uint16_t n;
    uint8_t sreg = SREG;
    cli();
    n = s_ev_dropped;
    SREG = sreg;
    return n;
}

ISR(TIMER1_OVF_vect) {
    s_frames++;
}

ISR(TIMER1_COMPA_vect) {
    if (!s_trig_on) {
        TCCR1A |= _BV(COM1A1); /* from the next BOTTOM on, the hardware drives the trigger */
        s_trig_on = 1;
    }
    /* s_frames is the index of the next frame. */
    if (s_pulse_state == PULSE_WAITING && s_pulse_frame == s_frames) {
        OCR1B = s_pulse_ocr; /* buffered: takes effect at the next BOTTOM */
        TIFR1 = _BV(OCF1B);
        TIMSK1 |= _BV(OCIE1B);
        TCCR1A |= _BV(COM1B1);
        s_pulse_state = PULSE_ARMED;
    } else if (s_pulse_state == PULSE_WAITING && s_pulse_frame < s_frames) {
        s_pulse_state = PULSE_IDLE; /* cannot happen by construction; never leave it stuck */
    }
}

ISR(TIMER1_COMPB_vect) {
    /* Only the match inside the pulse's own frame ends it (a match of the arming frame comes
     * before the pulse began). */
    if (s_pulse_state == PULSE_ARMED && s_frames == s_pulse_frame + 1) {
        TCCR1A &= (uint8_t)~(_BV(COM1B1) | _BV(COM1B0));
        TIMSK1 &= (uint8_t)~_BV(OCIE1B);
        OCR1B = 0; /* idle value below the trigger match: arming never sees OC1B high */
        s_pulse_state = PULSE_IDLE;
    }
}

ISR(INT0_vect) {
    uint32_t f;
    uint16_t t;
    uint8_t next;
    sample_locked(&f, &t);
    next = (uint8_t)((s_ev_head + 1) & (EVQ_SIZE - 1));
    if (next == s_ev_tail) {
        s_ev_dropped++;
        return;
    }
    s_evq[s_ev_head].channel = 0;
    s_evq[s_ev_head].edge = (EVT_PINR & _BV(EVT_BIT)) ? 1 : 0;
    s_evq[s_ev_head].frame_count = f;
    s_evq[s_ev_head].ticks = t;
    s_ev_head = next;
}
