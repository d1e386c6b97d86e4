/* Frame timer on Timer1, fast PWM mode 14 (TOP = ICR1).
 *
 * Frame trigger: OC1A is set by the hardware when the counter passes from TOP to 0 (BOTTOM) and
 * cleared at the OCR1A match, so every rising edge is exactly (TOP + 1) * prescaler CPU cycles
 * after the previous one, whatever the software does. Frame n (0-based) begins at the n+1-th BOTTOM
 * after START; `s_frames` counts those (TIMER1_OVF, flag set at TOP on the chip).
 *
 * The trigger output is connected (COM1A) only in the first OCR1A-match interrupt after START, so
 * the first rising edge is the first real BOTTOM, on the chip and in the simulator alike.
 *
 * Pulse channel 0: OC1B, connected only for the frame of the pulse. OCR1B is double-buffered in the
 * PWM modes (the new value takes effect at BOTTOM), so arming in frame n-1 (at its OCR1A match)
 * makes the hardware set OC1B at the start of frame n and clear it width_ticks later. The OCR1B
 * match interrupt of frame n disconnects it again.
 *
 * Event timestamps (GitHub issue 3). ATmega32U4: true input capture. Timer3 runs in lock-step
 * with Timer1 (CTC, TOP = OCR3A = ICR1, same prescaler, started together under GTCCR.TSM), so
 * ICR3 holds Timer1's tick count at the edge on ICP3 (D13), exact to the timer tick; the capture
 * interrupt then only has to find the frame the tick belongs to. ATmega328P (no free capture
 * unit): INT0 with a naked entry stub that latches TCNT1, TIFR1 and the pin in its first
 * instructions, so the timestamp lags the edge by a fixed FT_EVT_LATENCY_CYCLES, which is
 * subtracted. What remains is the jitter of entering an interrupt: the instruction under way and
 * any section that holds interrupts off. The frame interrupts therefore re-enable interrupts
 * first thing (the overflow count stays consistent through GPIOR0 bit 0, see TIMER1_OVF_vect);
 * the UART receive interrupt and the main loop's short cli() sections remain (hardware/README.md
 * gives the bounds).
 */
#include "frame_timer.h"

#include <avr/interrupt.h>
#include <avr/io.h>

#include "board.h"

#define PULSE_NOW 0xFFFFFFFFu
#define EVQ_SIZE 8 /* power of two */

enum { PULSE_IDLE = 0, PULSE_WAITING, PULSE_ARMED };

/* Trigger pulses started since the last STOP_RESET. Updated only by the hand-written overflow
 * interrupt, which sets OVF_BUSY_BIT (GPIOR0 bit 0, reachable by sbi/cbi without a register) from
 * the moment it is entered until the new value is stored: a nested interrupt counts it then. */
static volatile uint32_t s_frames;
#define OVF_BUSY_BIT 0
static volatile uint8_t s_running;
static volatile uint8_t s_trig_on; /* OC1A connected (first OCR1A match after START passed) */
static uint8_t s_cs = 2;           /* prescaler code == CS12:0 value */
static uint16_t s_top = 19999;     /* 100 Hz at 16 MHz, /8 */
static uint16_t s_trig_ocr;        /* trigger width - 1, in ticks */
/* STOP does not freeze the timer in the last STOP_GUARD_CYCLES before TOP: more than the cycles
 * from its check of TCNT1 to the write that stops the clock (interrupts off), so a new pulse cannot
 * begin at BOTTOM in between and be cut to a runt. */
#define STOP_GUARD_CYCLES 64u

static volatile uint8_t s_pulse_state;
static volatile uint32_t s_pulse_frame;
static volatile uint16_t s_pulse_ocr;

static volatile ft_event_t s_evq[EVQ_SIZE];
static volatile uint8_t s_ev_head, s_ev_tail;
static volatile uint16_t s_ev_dropped;

/* Frame count as the overflow interrupt will leave it; caller has interrupts disabled. */
static uint32_t frames_locked(void) {
    return s_frames + ((GPIOR0 & _BV(OVF_BUSY_BIT)) ? 1u : 0u);
}

#if !FT_EVT_ICP
/* FT_EVT_LATENCY_CYCLES in timer ticks, to the nearest tick. */
static uint16_t ft_evt_latency_ticks(uint8_t cs) {
    static const uint16_t div[6] = {1, 1, 8, 64, 256, 1024};
    return (uint16_t)((FT_EVT_LATENCY_CYCLES + div[cs] / 2) / div[cs]);
}
#endif

/* ICP3 catches one edge direction at a time: arm it for the edge away from the present level. */
#if FT_EVT_ICP
static void icp_arm(void) {
    if (EVT_PINR & _BV(EVT_BIT))
        TCCR3B &= (uint8_t)~_BV(ICES3);
    else
        TCCR3B |= _BV(ICES3);
    TIFR3 = _BV(ICF3);
}
#endif

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
#if FT_EVT_ICP
    /* Timer3: CTC with TOP = OCR3A, clock off until START; capture interrupt always on. */
    TCCR3A = 0;
    TCCR3B = _BV(WGM32);
    icp_arm();
    TIMSK3 = _BV(ICIE3);
#else
    EICRA = (uint8_t)((EICRA & ~(_BV(ISC01) | _BV(ISC00))) | _BV(ISC00));
    EIFR = _BV(INTF0);
    EIMSK |= _BV(INT0);
#endif
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
#if FT_EVT_ICP
    /* Lock-step: with the prescaler held (TSM), both counters start from 0 on the same clock
     * edge when TSM is released, and Timer3 wraps at the same TOP. */
    GTCCR = _BV(TSM) | _BV(PSRSYNC);
    TCCR3B = (uint8_t)(TCCR3B & ~(_BV(CS32) | _BV(CS31) | _BV(CS30)));
    OCR3A = s_top;
    TCNT3 = 0;
    TCCR3B = (uint8_t)(TCCR3B | s_cs);
    TCCR1B = (uint8_t)(_BV(WGM13) | _BV(WGM12) | s_cs);
    GTCCR = 0;
#else
    TCCR1B = (uint8_t)(_BV(WGM13) | _BV(WGM12) | s_cs);
#endif
    SREG = sreg;
}

void ft_timer_stop(void) {
    static const uint16_t div[6] = {1, 1, 8, 64, 256, 1024};
    uint8_t sreg = SREG;
    uint16_t guard = (uint16_t)((STOP_GUARD_CYCLES + div[s_cs] - 1) / div[s_cs]);
    if ((uint32_t)s_trig_ocr + guard >= s_top)
        guard = 0; /* a pulse over nearly the whole frame leaves no room for the guard */
    /* Never cut a trigger pulse short: a runt pulse can start a half exposure on some cameras and
     * would not have the width the cameras were set up for. In fast PWM the pin is high while
     * TCNT1 <= OCR1A (set at BOTTOM, cleared at the match), so wait, interrupts on, until the
     * counter has passed the match: at most the pulse width (~100 us at the default), and the next
     * rising edge is then at least half a frame away. The counter, not the pin, is read: it is the
     * same on the chip and in the simulator (simavr does not mirror OC1A into PINB). */
    for (;;) {
        uint16_t now;
        cli();
        if (!s_running || !s_trig_on)
            break;
        now = TCNT1;
        /* Past the match, and not so near TOP that BOTTOM (a new pulse) comes before the clock
         * stops below: at /1 that is a few dozen ticks, enough for a 42-cycle runt. */
        if (now > s_trig_ocr && now < (uint16_t)(s_top - guard))
            break;
        SREG = sreg;
    }
    if (s_running) {
        uint16_t t;
        TCCR1B = _BV(WGM13) | _BV(WGM12);
#if FT_EVT_ICP
        TCCR3B = (uint8_t)(TCCR3B & ~(_BV(CS32) | _BV(CS31) | _BV(CS30)));
#endif
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
 * be seen: the overflow flag is read before and after TCNT1 and the sample is retaken if it
 * changed, and a pending (not yet counted) overflow is added. TCNT1 == TOP is retaken too: on the
 * chip the flag (and the count) rises at TOP, one tick before the pulse, which would make that one
 * tick ambiguous. The wait is at most one timer tick. */
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
            *frames = frames_locked() + (p1 ? 1u : 0u);
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

/* Lock-free (one producer, the event interrupt; one consumer, the main loop; byte-wide indices):
 * the main loop polls this all the time, and a cli() here kept the event interrupt waiting for
 * up to 15 cycles (the dominant timestamp jitter before, measured with --irq-log). */
uint8_t ft_timer_pop_event(ft_event_t *ev) {
    uint8_t tail = s_ev_tail;
    const volatile ft_event_t *e;
    if (tail == s_ev_head)
        return 0;
    e = &s_evq[tail];
    ev->channel = e->channel;
    ev->edge = e->edge;
    ev->frame_count = e->frame_count;
    ev->ticks = e->ticks;
    s_ev_tail = (uint8_t)((tail + 1) & (EVQ_SIZE - 1)); /* the slot is the producer's again */
    return 1;
}

uint16_t ft_timer_events_dropped(void) {
    uint16_t n;
    uint8_t sreg = SREG;
    cli();
    n = s_ev_dropped;
    SREG = sreg;
    return n;
}

/* Entered with the overflow flag cleared by the hardware and s_frames not yet incremented. The
 * first instruction marks that (OVF_BUSY_BIT), the second lets the event interrupt in: from then
 * on anything nested reads frames_locked(). The store and the unmarking happen together with
 * interrupts off (6 instructions). Written by hand because a C ISR saves registers before its
 * first statement, which would keep interrupts off for ~25 cycles every frame. */
ISR(TIMER1_OVF_vect, ISR_NAKED) {
    __asm__ __volatile__(
        "sbi %[gpior], %[busy]\n\t"
        "sei\n\t"
        "push r24\n\t"
        "in r24, __SREG__\n\t"
        "push r24\n\t"
        "push r25\n\t"
        "push r26\n\t"
        "push r27\n\t"
        "lds r24, %[f]\n\t"
        "lds r25, %[f]+1\n\t"
        "lds r26, %[f]+2\n\t"
        "lds r27, %[f]+3\n\t"
        "subi r24, 0xFF\n\t" /* + 1: subtract -1 with the borrow chained */
        "sbci r25, 0xFF\n\t"
        "sbci r26, 0xFF\n\t"
        "sbci r27, 0xFF\n\t"
        "cli\n\t"
        "sts %[f], r24\n\t"
        "sts %[f]+1, r25\n\t"
        "sts %[f]+2, r26\n\t"
        "sts %[f]+3, r27\n\t"
        "cbi %[gpior], %[busy]\n\t"
        "pop r27\n\t"
        "pop r26\n\t"
        "pop r25\n\t"
        "pop r24\n\t"
        "out __SREG__, r24\n\t" /* saved with I set: interrupts back on from here */
        "pop r24\n\t"
        "reti\n\t" ::[gpior] "I"(_SFR_IO_ADDR(GPIOR0)),
        [busy] "I"(OVF_BUSY_BIT), [f] "i"(&s_frames));
}

/* Interruptible (ISR_NOBLOCK): an input edge during this handler is timestamped at once. It reads
 * the frame count with interrupts off, as an overflow could nest here. */
ISR(TIMER1_COMPA_vect, ISR_NOBLOCK) {
    uint32_t next;
    cli();
    next = frames_locked(); /* index of the next frame */
    sei();
    if (!s_trig_on) {
        TCCR1A |= _BV(COM1A1); /* from the next BOTTOM on, the hardware drives the trigger */
        s_trig_on = 1;
    }
    if (s_pulse_state == PULSE_WAITING && s_pulse_frame == next) {
        OCR1B = s_pulse_ocr; /* buffered: takes effect at the next BOTTOM */
        TIFR1 = _BV(OCF1B);
        TIMSK1 |= _BV(OCIE1B);
        TCCR1A |= _BV(COM1B1);
        s_pulse_state = PULSE_ARMED;
    } else if (s_pulse_state == PULSE_WAITING && s_pulse_frame < next) {
        s_pulse_state = PULSE_IDLE; /* cannot happen by construction; never leave it stuck */
    }
}

ISR(TIMER1_COMPB_vect, ISR_NOBLOCK) {
    uint32_t f;
    cli();
    f = frames_locked();
    sei();
    /* Only the match inside the pulse's own frame ends it (a match of the arming frame comes
     * before the pulse began). */
    if (s_pulse_state == PULSE_ARMED && f == s_pulse_frame + 1) {
        TCCR1A &= (uint8_t) ~(_BV(COM1B1) | _BV(COM1B0));
        TIMSK1 &= (uint8_t)~_BV(OCIE1B);
        OCR1B = 0; /* idle value below the trigger match: arming never sees OC1B high */
        s_pulse_state = PULSE_IDLE;
    }
}

static void push_event(uint8_t edge, uint32_t f, uint16_t t) {
    uint8_t next = (uint8_t)((s_ev_head + 1) & (EVQ_SIZE - 1));
    if (next == s_ev_tail) {
        s_ev_dropped++;
        return;
    }
    s_evq[s_ev_head].channel = 0;
    s_evq[s_ev_head].edge = edge;
    s_evq[s_ev_head].frame_count = f;
    s_evq[s_ev_head].ticks = t;
    s_ev_head = next;
}

#if FT_EVT_ICP
/* ICR3 = Timer1's tick at the edge (lock-step). This handler runs later, by at most a frame:
 * sample the clock now and go back one frame if the counter wrapped since the capture. */
ISR(TIMER3_CAPT_vect) {
    uint16_t cap = ICR3;
    uint8_t edge = (TCCR3B & _BV(ICES3)) ? 1 : 0;
    uint32_t f;
    uint16_t t;
    TCCR3B ^= _BV(ICES3); /* catch the other edge next; the flag must be cleared after a change */
    TIFR3 = _BV(ICF3);
    sample_locked(&f, &t);
    if (s_running && t < cap)
        f--;
    else if (!s_running)
        cap = t;
    push_event(edge, f, cap);
}
#else
/* Latched by the INT0 stub below. */
static volatile uint16_t s_cap_tcnt;
static volatile uint8_t s_cap_tifr, s_cap_gpior, s_cap_pin;

void int0_body(void) __asm__("__vector_int0_body") __attribute__((signal, used));

/* The timestamp is taken here, before any register but r24 is saved: TCNT1 is read
 * FT_EVT_LATENCY_CYCLES after the edge (frame_timer.h), whatever the rest of the handler costs. */
ISR(INT0_vect, ISR_NAKED) {
    __asm__ __volatile__(
        "push r24\n\t"
        "lds r24, %[tl]\n\t" /* low byte first: latches the high byte */
        "sts %[ct], r24\n\t"
        "lds r24, %[th]\n\t"
        "sts %[ct]+1, r24\n\t"
        "in r24, %[tifr]\n\t"
        "sts %[cf], r24\n\t"
        "in r24, %[gpior]\n\t"
        "sts %[cg], r24\n\t"
        "in r24, %[pin]\n\t"
        "sts %[cp], r24\n\t"
        "pop r24\n\t"
        "jmp __vector_int0_body\n\t" ::[tl] "i"(&TCNT1L),
        [th] "i"(&TCNT1H), [tifr] "I"(_SFR_IO_ADDR(TIFR1)), [gpior] "I"(_SFR_IO_ADDR(GPIOR0)),
        [pin] "I"(_SFR_IO_ADDR(EVT_PINR)), [ct] "i"(&s_cap_tcnt), [cf] "i"(&s_cap_tifr),
        [cg] "i"(&s_cap_gpior), [cp] "i"(&s_cap_pin));
}

/* Runs with interrupts off (a signal handler), right after the stub. */
void int0_body(void) {
    uint16_t t = s_cap_tcnt;
    uint32_t f = s_frames;
    uint8_t edge = (s_cap_pin & _BV(EVT_BIT)) ? 1 : 0;
    if (s_running) {
        uint16_t comp = ft_evt_latency_ticks(s_cs);
        if (s_cap_gpior & _BV(OVF_BUSY_BIT))
            f++;
        /* A pending overflow belongs to this sample if the counter is past BOTTOM already; read
         * near TOP it is the next one (on the chip the flag rises at TOP). */
        if ((s_cap_tifr & _BV(TOV1)) && t < s_top / 2)
            f++;
        if (t >= comp) {
            t -= comp;
        } else {
            t = (uint16_t)(t + s_top + 1 - comp);
            f--;
        }
    }
    push_event(edge, f, t);
}
#endif
