/* DVS USB bridge firmware (ATmega32U4, 16 MHz): AER capture -> DVS128 words -> bulk-IN 0x86.
 *
 * One polling loop, no interrupt in the event path (the sync input's tiny INT6 handler only stamps
 * the pulse). Per event: Timer3's input capture has stamped /REQ's falling edge (exact), the loop
 * reads the two address bytes and ICR3, does the four-phase handshake (/ACK low, wait /REQ high,
 * /ACK high) and stores the 4-byte word, preferably straight into the USB endpoint bank (2 cycles
 * a byte); when no bank is free the words go to a 1 KiB SRAM FIFO that is copied into banks as they
 * free up. A full FIFO drops whole events (counted, status request); WRAP, RESET and SYNC words
 * have a reserve and are never dropped silently.
 *
 * Words (protocol/SPEC.md section 2): byte 0 = x << 1 | polarity, byte 1 = y | SYNC << 7,
 * u16 LE = 14-bit us timestamp | RESET << 14 | WRAP << 15. ts = Timer3 ticks >> 1.
 * Wraps: an event whose ts is below the last one's follows a counter wrap, so a WRAP word goes
 * first. With no events the loop reads TCNT3 itself often enough to never miss one.
 */
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/wdt.h>
#include <stdint.h>
#include <string.h>

#include "board.h"
#include "dvs_bridge.h"
#include "flytrack/dvs.h" /* the word's bits, as the SPEC and the host's codecs have them */
#include "usb_seam.h"

#define FIFO_BYTES 1024u
#define FIFO_RESERVE 8u    /* words kept free for WRAP / RESET / SYNC words */
#define WORDS_PER_BANK 16u /* 64-byte bulk packets */
#define FLUSH_TICKS 2000u  /* a partly filled bank goes out after 1 ms */
/* INT6 entry to its TCNT3 read: 4 (response) + 3 (jmp) + 2 (push) + 2 (lds), rounded to ticks */
#define SYNC_LATENCY_TICKS 1u
/* slave reset: cycles from its TCNT3 read to the write, in ticks */
#define SLAVE_WRITE_TICKS 3u

static uint8_t fifo[FIFO_BYTES] __attribute__((aligned(1024)));

/* Loop state, kept in registers by the hot loop and stored here around the slow path. */
static struct {
    uint8_t *head, *tail, *stop; /* FIFO write / read pointers; events stop at `stop` */
    uint16_t last;               /* ts (us) of the last word or idle reading */
    uint8_t left;                /* words still free in the bank being filled (0: none) */
    uint8_t pend_wraps, pend_reset;
    uint16_t t0; /* Timer3 when the open, partly filled bank was first seen (flush_old_bank) */
    uint8_t t0_valid, seen_left;
    uint8_t step;       /* slow_step's next task */
    uint8_t fifo_steps; /* events through the FIFO path since its last slow_step */
    uint8_t stop_req;   /* a slow_step run from slow_put saw START or STOP */
} C;

static struct {
    uint32_t overflow, sync_events, sync_missed, clamped;
    uint16_t fifo_max;
    uint8_t running, master, slave_armed;
    uint8_t sync_seen;
} S;

/* written by the INT6 handler */
#define SYNC_RING 4                     /* pulses the handler keeps until the loop takes them */
volatile uint8_t sync_seq;              /* pulses seen by the handler */
volatile uint16_t sync_ring[SYNC_RING]; /* their TCNT3 values, pulse i at [i % SYNC_RING] */

static uint8_t bias[DVS_BIAS_BYTES];

/* Timer3's 16-bit registers share one TEMP byte (the high byte, latched when the low byte is read),
 * and the INT6 handler reads TCNT3: a 16-bit read it interrupts would get the handler's high byte.
 * So the slow path reads them with interrupts off (the loop always runs with them on). The event
 * path reads ICR3 without: the handler ends by reading ICR3L, which latches ICR3's high byte again,
 * so an ICR3 read it interrupted still gets the right one. */
static inline uint16_t icr3(void) {
    cli();
    uint16_t v = ICR3;
    sei();
    return v;
}
static inline uint16_t tcnt3(void) {
    cli();
    uint16_t v = TCNT3;
    sei();
    return v;
}

static inline uint8_t *fifo_next(uint8_t *p) {
    return (uint8_t *)(((uint16_t)(p + 4) & (FIFO_BYTES - 1)) | (uint16_t)fifo);
}
static inline uint16_t fifo_words(void) {
    return (uint16_t)((uint16_t)(C.head - C.tail) & (FIFO_BYTES - 1)) >> 2;
}

/* Events may fill the FIFO up to FIFO_RESERVE free words, and not at all while special words wait.
 */
static void fifo_limits(void) {
    uint16_t used = fifo_words();
    if (used > S.fifo_max)
        S.fifo_max = used;
    if (C.pend_wraps || C.pend_reset || used >= FIFO_BYTES / 4 - 1 - FIFO_RESERVE)
        C.stop = C.head;
    else
        C.stop = (uint8_t *)(((uint16_t)(C.tail - 4 * (FIFO_RESERVE + 1)) & (FIFO_BYTES - 1)) |
                             (uint16_t)fifo);
}

/* A word in stream order: into the open bank, else the FIFO. 0 if the FIFO has no room at all. */
static uint8_t put_word(uint8_t b0, uint8_t b1, uint16_t t) {
    if (C.left) {
        usb_bulk_in_put(b0);
        usb_bulk_in_put(b1);
        usb_bulk_in_put((uint8_t)t);
        usb_bulk_in_put((uint8_t)(t >> 8));
        if (--C.left == 0) {
            usb_bulk_in_send();
            C.left = usb_bulk_in_ready() ? WORDS_PER_BANK : 0;
        }
        return 1;
    }
    uint8_t *n = fifo_next(C.head);
    if (n == C.tail)
        return 0;
    C.head[0] = b0;
    C.head[1] = b1;
    C.head[2] = (uint8_t)t;
    C.head[3] = (uint8_t)(t >> 8);
    C.head = n;
    fifo_limits();
    return 1;
}

static void put_wrap(void) {
    if (C.pend_wraps || C.pend_reset || !put_word(0, 0, FT_DVS_WRAP_BIT))
        C.pend_wraps++;
    fifo_limits();
}

static void put_reset(void) {
    C.pend_wraps = 0; /* a reset makes the wraps before it meaningless */
    if (C.pend_reset || !put_word(0, 0, FT_DVS_RESET_BIT))
        C.pend_reset = 1;
    fifo_limits();
}

/* Pending special words go out once there is room, after what the FIFO holds. */
static void flush_pending(void) {
    if (C.pend_reset && put_word(0, 0, FT_DVS_RESET_BIT))
        C.pend_reset = 0;
    while (!C.pend_reset && C.pend_wraps && put_word(0, 0, FT_DVS_WRAP_BIT))
        C.pend_wraps--;
    fifo_limits();
}

/* Copies FIFO words into a free bank; with the FIFO empty, the next bank is filled directly. */
static void __attribute__((noinline)) drain(void) {
    if (C.left)
        return;
    if (!usb_bulk_in_ready())
        return;
    /* up to a bank's worth, in at most two runs that do not cross the FIFO's end */
    uint8_t *p = C.tail;
    uint16_t used = fifo_words();
    uint8_t n = used < WORDS_PER_BANK ? (uint8_t)used : WORDS_PER_BANK;
    uint8_t run = (uint8_t)((uint16_t)(fifo + FIFO_BYTES - p) >> 2);
    uint8_t left = (uint8_t)(WORDS_PER_BANK - n);
    if (run > n)
        run = n;
    n -= run;
    while (run--) {
        usb_bulk_in_put(*p++);
        usb_bulk_in_put(*p++);
        usb_bulk_in_put(*p++);
        usb_bulk_in_put(*p++);
    }
    if (p == fifo + FIFO_BYTES)
        p = fifo;
    while (n--) {
        usb_bulk_in_put(*p++);
        usb_bulk_in_put(*p++);
        usb_bulk_in_put(*p++);
        usb_bulk_in_put(*p++);
    }
    C.tail = p;
    C.left = left; /* the rest of this bank is filled directly (the FIFO is empty then) */
    if (!left)
        usb_bulk_in_send();
    flush_pending();
}

static void sync_word(uint8_t pre_wrap);
static uint8_t sync_emit(uint16_t raw, uint8_t pre_wrap, uint8_t pending, uint16_t icr);
static uint8_t sync_take(uint8_t upto, uint16_t *raw);
static uint8_t slow_step(void);
static uint8_t control(void);

/* An event with no bank open. With the FIFO empty, wait a little for the host to free a bank (the
 * sensor waits on its handshake meanwhile: AER backpressure) rather than store the word and copy it
 * later, which costs a third more cycles an event; only a host that stays away longer (~90 us)
 * makes the FIFO fill. A full FIFO drops the event whole and counts it. steps: the slow path may
 * run from here (not when called from a request's own work). */
static void __attribute__((noinline)) slow_put(uint8_t a0, uint8_t a1, uint16_t t, uint8_t steps) {
    uint8_t k = 255;
    for (;;) {
        if (C.left) { /* a bank is open (a slow-path task may have opened one) */
            put_word(a0, a1, t);
            goto stored;
        }
        if (C.tail != C.head || C.pend_wraps || C.pend_reset)
            break; /* the FIFO is in use: the event goes behind what it holds */
        if (usb_bulk_in_ready()) {
            C.left = WORDS_PER_BANK;
            if (sync_seq != S.sync_seen)
                sync_word(1); /* a pulse that came while we waited (pre-wrap: the event is held) */
            put_word(a0, a1, t);
            goto stored;
        }
        if (!--k || (steps && usb_control_pending()))
            break; /* a request: the event goes to the FIFO so that the request can be served */
        /* Nothing else runs while the event is held: a pulse waits for the bank (above), a
         * request makes the event go to the FIFO (below). */
    }
    if (C.head == C.stop)
        S.overflow++;
    else
        put_word(a0, a1, t);
    if (usb_bulk_in_ready())
        drain();
    /* With the sensor never idle the loop would not get to the slow path: one task every 8th
     * event through the FIFO, and a waiting request at once (the event is stored, nothing held). */
    if (steps && sync_seq != S.sync_seen)
        sync_word(0);
    if (steps && usb_control_pending()) {
        if (control())
            C.stop_req = 1;
    } else if (steps && !(++C.fifo_steps & 7) && slow_step()) {
        C.stop_req = 1;
    }
stored:
    return;
}

/* The event whose edge Timer3 has captured, served here in the slow path (before a timestamp reset,
 * so that it keeps the epoch it was stamped in). */
static void serve_one(void) {
    uint8_t a0 = ADDR0_PIN, a1 = ADDR1_PIN & (uint8_t)~FT_DVS_SYNC_BIT;
    uint16_t t = (icr3() >> 1) & FT_DVS_TS_MASK;
    TIFR3 = _BV(ICF3);
    ACK_PORT &= (uint8_t)~_BV(ACK_BIT);
    while (!(REQ_PIN & _BV(REQ_BIT)))
        ;
    ACK_PORT |= _BV(ACK_BIT);
    if (t < C.last)
        put_wrap();
    C.last = t;
    if (C.left)
        put_word(a0, a1, t);
    else
        slow_put(a0, a1, t, 0);
}

/* Timer3 restarted from start_ticks (now), and a RESET word. Events keep the epoch they were
 * stamped in: one waiting is served first; one whose edge came during the restart itself (its ICR3
 * holds an old-epoch value above the new count) is served before the RESET word too. */
static void timer_zero(uint8_t from_pulse, uint16_t pulse_ticks) {
    uint16_t raw;
    if (TIFR3 & _BV(ICF3))
        serve_one();
    /* The counter keeps running: the prescaler restarts (PSRSYNC) and the count is written, so the
     * next tick is a whole tick after this write. */
    cli(); /* a sync pulse is of the old epoch or of the new one, never in between */
    uint8_t seq = sync_seq;
    uint16_t start_ticks = 0;
    if (from_pulse) /* slave: time zero is the pulse; the count is the ticks since, at the write */
        start_ticks = (uint16_t)((TCNT3 - pulse_ticks + SLAVE_WRITE_TICKS) & TS_TOP);
    GTCCR = _BV(PSRSYNC);
    TCNT3 = start_ticks;
    sei();
    if ((TIFR3 & _BV(ICF3)) && icr3() > tcnt3())
        serve_one();
    /* pulses of the old epoch not yet taken go before the RESET word */
    uint8_t armed = S.slave_armed;
    S.slave_armed = 0;
    while (S.running && sync_take(seq, &raw))
        sync_emit(raw, 0, 0, 0);
    S.slave_armed = armed;
    put_reset();
    C.last = start_ticks >> 1;
}

/* The oldest pulse not yet taken (of those before pulse number `upto`), its TCNT3 value in *raw:
 * 0 if none. More than SYNC_RING waiting: the oldest were overwritten, counted as missed. */
static uint8_t sync_take(uint8_t upto, uint16_t *raw) {
    uint8_t n = (uint8_t)(upto - S.sync_seen);
    if (!n)
        return 0;
    if (n > SYNC_RING) {
        S.sync_missed += n - SYNC_RING;
        S.sync_seen = (uint8_t)(upto - SYNC_RING);
    }
    cli();
    *raw = sync_ring[S.sync_seen & (SYNC_RING - 1)];
    sei();
    return 1;
}

/* The waiting sync pulses as SYNC words, oldest first. One waits if an event stamped before it is
 * not yet read. pre_wrap (the event path has just seen a counter wrap, or an event is held): only
 * pulses from before that wrap, which must precede the WRAP word. */
static uint8_t sync_emit(uint16_t raw, uint8_t pre_wrap, uint8_t pending, uint16_t icr);

static void sync_word(uint8_t pre_wrap) {
    uint16_t raw;
    if (!S.running)
        return;
    /* only pulses stamped before the look at ICF3: one stamped later may follow an edge that
     * comes after that look */
    uint8_t upto = sync_seq;
    uint8_t pending = (TIFR3 & _BV(ICF3)) != 0;
    uint16_t icr = icr3();
    while (sync_take(upto, &raw) && sync_emit(raw, pre_wrap, pending, icr))
        ;
}

/* The pulse the handler stamped `raw` (the oldest not taken) as a SYNC word; 0 if it must wait. */
static uint8_t sync_emit(uint16_t raw, uint8_t pre_wrap, uint8_t pending, uint16_t icr) {
    uint16_t ticks = (uint16_t)((raw - SYNC_LATENCY_TICKS) & TS_TOP);
    if (pending && (uint16_t)((ticks - icr) & TS_TOP) < 0x4000u)
        return 0; /* the pulse came after the waiting event's edge */
    uint16_t ts = ticks >> 1;
    uint16_t d = (uint16_t)((ts - C.last) & FT_DVS_TS_MASK);
    uint8_t after_wrap = d < 0x2000u && ts < C.last;
    if (pre_wrap && (S.slave_armed || after_wrap))
        return 0; /* it goes out after the WRAP word, from the slow path */
    S.sync_seen++;
    if (S.slave_armed) {
        /* slave: this pulse is time zero. TCNT3 = ticks elapsed since it, kept running */
        S.slave_armed = 0;
        timer_zero(1, ticks);
        ts = 0;
    } else if (d < 0x2000u) { /* at or after the last word's time */
        if (after_wrap)
            put_wrap();
        C.last = ts;
    } else if (ts > C.last) { /* before a WRAP already sent: the nearest time it can carry */
        ts = 0;
        S.clamped++;
    }
    if (put_word(0, FT_DVS_SYNC_BIT, ts))
        S.sync_events++;
    else
        S.sync_missed++;
    return 1;
}

/* The counter may wrap with no event to show it: read it (then check no edge came first). */
static void idle_wrap(void) {
    uint16_t now = (tcnt3() >> 1) & FT_DVS_TS_MASK;
    if (TIFR3 & _BV(ICF3))
        return;
    if (now < C.last)
        put_wrap();
    C.last = now;
}

/* A partly filled bank goes out once it has been open FLUSH_TICKS (as first seen here), so that a
 * slow trickle of events is not held back until 16 have come. A bank opened since the last look
 * (more room than then) restarts the clock. */
static void flush_old_bank(void) {
    uint8_t l = C.left;
    if (!l || l == WORDS_PER_BANK) {
        C.t0_valid = 0;
    } else {
        uint16_t now = tcnt3();
        if (!C.t0_valid || l > C.seen_left) {
            C.t0 = now;
            C.t0_valid = 1;
        } else if ((uint16_t)((now - C.t0) & TS_TOP) >= FLUSH_TICKS) {
            usb_bulk_in_send();
            C.left = 0;
            C.t0_valid = 0;
            drain();
        }
    }
    C.seen_left = l;
}

static void shift_biases(void) {
    for (uint8_t i = 0; i < DVS_BIAS_BYTES; i++)
        for (uint8_t m = 0x80; m; m >>= 1) {
            if (bias[i] & m)
                BIAS_PORT |= _BV(BIAS_BIT);
            else
                BIAS_PORT &= (uint8_t)~_BV(BIAS_BIT);
            BIAS_PORT |= _BV(BIAS_CLK);
            BIAS_PORT &= (uint8_t)~_BV(BIAS_CLK);
        }
    BIAS_PORT |= _BV(BIAS_LATCH);
    BIAS_PORT &= (uint8_t)~_BV(BIAS_LATCH);
}

static void put_u32(uint8_t *p, uint32_t v) {
    for (uint8_t i = 0; i < 4; i++, v >>= 8)
        p[i] = (uint8_t)v;
}

/* One vendor request. Returns 1 if streaming was started or stopped. */
static uint8_t control(void) {
    usb_setup_t s;
    uint8_t data[DVS_BIAS_BYTES];
    if (!usb_control_poll(&s, data, sizeof data))
        return 0;
    if ((s.bmRequestType & 0x60) != 0x40) { /* vendor requests only */
        usb_control_stall();
        return 0;
    }
    switch (s.bRequest) {
    case DVS_VR_START:
        usb_control_reply(0, 0);
        if (S.running)
            return 0;
        S.running = 1;
        S.slave_armed = !S.master;
        fifo_limits();
        if (S.master)
            timer_zero(0, 0);
        return 1;
    case DVS_VR_STOP:
        usb_control_reply(0, 0);
        if (!S.running)
            return 0;
        S.running = 0;
        return 1;
    case DVS_VR_BIASES:
        if (s.wLength != DVS_BIAS_BYTES || (s.bmRequestType & 0x80)) {
            usb_control_stall();
            return 0;
        }
        memcpy(bias, data, sizeof bias);
        usb_control_reply(0, 0);
        shift_biases();
        return 0;
    case DVS_VR_RESET_TS:
        usb_control_reply(0, 0);
        if (S.running)
            timer_zero(0, 0);
        return 0;
    case DVS_VR_RESET_ARRAY:
        usb_control_reply(0, 0);
        BIAS_PORT |= _BV(ARRAY_RESET);
        for (volatile uint8_t i = 0; i < 20; i++)
            ;
        BIAS_PORT &= (uint8_t)~_BV(ARRAY_RESET);
        return 0;
    case DVS_VR_TS_MASTER:
        S.master = s.wValue & 1u;
        S.slave_armed = S.running && !S.master;
        usb_control_reply(0, 0);
        return 0;
    case DVS_VR_FT_STATUS: {
        uint8_t r[DVS_STATUS_SIZE];
        put_u32(r, S.overflow);
        put_u32(r + 4, S.sync_events);
        put_u32(r + 8, S.sync_missed);
        put_u32(r + 12, S.clamped);
        r[16] = (uint8_t)S.fifo_max;
        r[17] = (uint8_t)(S.fifo_max >> 8);
        r[18] = S.running;
        r[19] = S.master;
        usb_control_reply(r, (uint8_t)(s.wLength < sizeof r ? s.wLength : sizeof r));
        return 0;
    }
    default:
        usb_control_stall();
        return 0;
    }
}

/* Everything but the event path, one short task at a time (each well under 100 cycles, bar a
 * request's own work), so that an event is never kept waiting long: when no event is waiting, every
 * 8th bank while events stream, every 8th event through the FIFO path. Returns 1 when streaming
 * stops or restarts. */
static uint8_t __attribute__((noinline)) slow_step(void) {
    uint8_t r = 0;
    if (++C.step >= 8)
        C.step = 0;
    if (C.step & 1) /* requests every other step */
        return control();
    switch (C.step) {
    case 0:
        if (sync_seq != S.sync_seen)
            sync_word(0);
        break;
    case 2:
        idle_wrap();
        break;
    case 4:
        drain();
        break;
    default:
        flush_old_bank();
        break;
    }
    return r;
}

/* The event loop: hot path inline, locals in registers. */
static void capture(void) {
    uint16_t last = C.last;
    uint8_t left = C.left;
    uint8_t banks = 0;
    for (;;) {
        if (TIFR3 & _BV(ICF3)) {
            uint8_t a0 = ADDR0_PIN;
            uint8_t a1 = ADDR1_PIN;
            uint16_t t = ICR3;
            TIFR3 = _BV(ICF3);
            ACK_PORT &= (uint8_t)~_BV(ACK_BIT);
            a1 &= (uint8_t)~FT_DVS_SYNC_BIT; /* /REQ (PD7) is low here; bit 7 is the SYNC flag */
            t >>= 1;
            while (!(REQ_PIN & _BV(REQ_BIT)))
                ;
            ACK_PORT |= _BV(ACK_BIT);
            if (t < last) {
                C.left = left;
                C.last = last;
                if (sync_seq != S.sync_seen)
                    sync_word(1); /* a pulse from before the wrap goes first */
                put_wrap();
                left = C.left;
            }
            last = t;
            if (left) {
                usb_bulk_in_put(a0);
                usb_bulk_in_put(a1);
                usb_bulk_in_put((uint8_t)t);
                usb_bulk_in_put((uint8_t)(t >> 8));
                if (--left)
                    continue;
                usb_bulk_in_send();
                left = usb_bulk_in_ready() ? WORDS_PER_BANK : 0;
                /* while events stream, a waiting sync pulse goes out at each bank and the slow
                 * path's other tasks run one at a time, one every 8th bank */
                if (left) {
                    if (sync_seq != S.sync_seen) {
                        C.left = left;
                        C.last = last;
                        sync_word(0);
                        left = C.left;
                        last = C.last;
                    }
                    if (!(++banks & 7)) {
                        C.left = left;
                        C.last = last;
                        uint8_t r = slow_step();
                        left = C.left;
                        last = C.last;
                        if (r)
                            return;
                    }
                }
                continue; /* no bank free: the next event waits for one in slow_put */
            } else {
                C.left = left;
                C.last = last;
                slow_put(a0, a1, t, 1);
                left = C.left;
                last = C.last;
                if (C.stop_req) {
                    C.stop_req = 0;
                    return;
                }
                continue;
            }
        }
        /* no event waiting: one short slow-path task, then look again */
        C.last = last;
        C.left = left;
        if (slow_step())
            return;
        last = C.last;
        left = C.left;
    }
}

/* Stopped: events are acknowledged and discarded (the sensor never hangs on its bus), what is
 * buffered still goes out, requests are served. */
static void stopped(void) {
    for (;;) {
        if (TIFR3 & _BV(ICF3)) {
            TIFR3 = _BV(ICF3);
            ACK_PORT &= (uint8_t)~_BV(ACK_BIT);
            while (!(REQ_PIN & _BV(REQ_BIT)))
                ;
            ACK_PORT |= _BV(ACK_BIT);
        }
        if (C.left && C.left < WORDS_PER_BANK) {
            usb_bulk_in_send();
            C.left = 0;
        }
        drain();
        if (C.left == WORDS_PER_BANK)
            C.left = 0; /* nothing to send: no bank is held open while stopped */
        S.sync_seen = sync_seq;
        if (control())
            return;
    }
}

int main(void) {
    /* a bootloader may leave the watchdog on, and a fresh chip runs at f/8 (CKDIV8 fuse) */
    MCUSR &= (uint8_t)~_BV(WDRF);
    wdt_disable();
    CLKPR = _BV(CLKPCE);
    CLKPR = 0;
    DDRB = 0;
    PORTB = 0;
    DDRD = 0;
    PORTD = _BV(REQ_BIT); /* pull-up: an unplugged sensor reads as idle */
    ACK_DDR |= _BV(ACK_BIT);
    ACK_PORT |= _BV(ACK_BIT) | _BV(ICP_BIT);
    BIAS_DDR |= _BV(BIAS_CLK) | _BV(BIAS_BIT) | _BV(BIAS_LATCH) | _BV(ARRAY_RESET);
    SYNC_PORT &= (uint8_t)~_BV(SYNC_BIT);
    /* Timer3: CTC (TOP = OCR3A), capture on /REQ's falling edge, f_cpu / 8 */
    TCCR3A = 0;
    OCR3A = TS_TOP;
    TCCR3B = _BV(WGM32) | _BV(CS31);
    EICRB = _BV(ISC61) | _BV(ISC60); /* INT6 rising edge */
    EIFR = _BV(INTF6);
    EIMSK = _BV(INT6);
    C.head = C.tail = fifo;
    S.master = 1;
    fifo_limits();
    usb_seam_init();
    sei();
    for (;;) {
        if (S.running)
            capture();
        else
            stopped();
    }
}

/* Sync pulse: TCNT3 read in the handler's first instructions (fixed latency, SYNC_LATENCY_TICKS),
 * kept in sync_ring[sync_seq % SYNC_RING]; the main loop turns the pulses into SYNC words, oldest
 * first, and counts any that were overwritten before it took them. */
ISR(INT6_vect, ISR_NAKED) {
    __asm__ volatile(
        "push r24\n\t"
        "lds r24, %[tl]\n\t"
        "push r25\n\t"
        "lds r25, %[th]\n\t"
        "push r30\n\t"
        "in r30, __SREG__\n\t"
        "push r30\n\t"
        "push r31\n\t"
        "lds r30, sync_seq\n\t"
        "andi r30, %[mask]\n\t"
        "lsl r30\n\t"
        "ldi r31, 0\n\t"
        "subi r30, lo8(-(sync_ring))\n\t"
        "sbci r31, hi8(-(sync_ring))\n\t"
        "st Z+, r24\n\t"
        "st Z, r25\n\t"
        "lds r30, sync_seq\n\t"
        "subi r30, 0xFF\n\t"
        "sts sync_seq, r30\n\t"
        "lds r30, %[il]\n\t" /* re-latch TEMP with ICR3's high byte (see icr3) */
        "pop r31\n\t"
        "pop r30\n\t"
        "out __SREG__, r30\n\t"
        "pop r30\n\t"
        "pop r25\n\t"
        "pop r24\n\t"
        "reti\n\t" ::[tl] "i"(_SFR_MEM_ADDR(TCNT3L)),
        [th] "i"(_SFR_MEM_ADDR(TCNT3H)), [mask] "i"(SYNC_RING - 1), [il] "i"(_SFR_MEM_ADDR(ICR3L)));
}
