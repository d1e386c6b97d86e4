/* flytrack_trigger_sim: runs the unchanged trigger firmware .elf in simavr.
 *
 * - The firmware's UART is connected to a pseudo-terminal. The pty's slave path is printed on
 * stdout as "PTY /dev/pts/N" (and written to --pty-file). simavr's own uart_pty part is not used:
 * in 1.6 its thread spins when a client closes the port (read() = -1 taken as a length) so the
 * process can never be stopped, it shares the /tmp/simavr-uart0 link between all simavrs on the
 * machine, and it moves bytes from a second thread. Here the main loop moves the bytes
 * (non-blocking master fd; the harness keeps the slave open so clients may come and go).
 * - Every edge of the trigger, pulse and stimulus outputs (and of the injected event input) is
 *   written to the edge log, one line per edge, line-buffered (the path may be a FIFO):
 *
 *       # flytrack-trigger-sim 1 mcu=atmega328p f_cpu=16000000
 *       <cycle> <signal> <level>
 *
 *   cycle: CPU cycle of the edge since reset (time = cycle / f_cpu seconds); signal: trigger,
 *   pulse0, out1, out2, out3 or event_in; level: 0 or 1. Lines starting with '#' are comments.
 *   Trigger and pulse edges come from Timer1's compare hardware and are logged at the cycle the
 *   simulated timer scheduled them (simavr handles timer events after the instruction under way,
 *   up to a few cycles late; the log gives the hardware's cycle, not the simulator's step).
 * - --realtime paces the simulation to the wall clock (so a host clock model sees real elapsed
 *   time); otherwise it runs as fast as it can. Paced, the harness costs little CPU although the
 *   firmware busy-polls: when the firmware is in an idle loop (back at the same instruction with
 *   every register, I/O register and RAM byte unchanged, having raised no interrupt, pin or UART
 *   byte on the way), running that loop on changes nothing until the next simavr cycle timer (timer
 *   compare, UART byte, injected edge, watchdog) or a host byte, so the harness advances the cycle
 *   count by whole loop lengths up to the wall clock (never past it: a host byte lands at the cycle
 *   it arrived) and sleeps in ppoll until the next timer is due or the pty has input. While the
 *   firmware works it is emulated at most 50 us ahead of the wall clock. UART bytes reach the pty
 *   when their stop bit ends on the simulated wire, not earlier. An edge-log comment
 *   "# paced t0_monotonic=S t0_realtime=S ppm=P drift_ppm_per_s=D" gives the wall time at which
 *   cycle 0 was due and the simulated crystal's error.
 * - --ppm P and --drift-ppm-per-s D (paced only) make the simulated crystal run off its nominal
 *   frequency as a real one does: at wall time t after the start it runs at
 *   f_cpu x (1 + (P + D t) 1e-6), so cycle c is due at the t where
 *   c = f_cpu (t + 1e-6 (P t + D t^2 / 2)). A host clock model must then recover that rate.
 * - --event-period N injects a square wave on the event input pin (INT0), first rising edge at
 *   --event-phase, high for --event-high cycles, to test the event timestamps.
 *
 * - An interrupt's entry costs 4 cycles, as on the chip (simavr 1.6 charges none).
 * - --irq-log adds the entry and exit of every interrupt to the edge log as comment lines
 *   "# irq <vector> enter|exit <cycle> pc=<addr>" (to see what delays an event timestamp).
 *
 * simavr 1.6 does not model GTCCR.TSM (timer synchronisation mode: the prescaler is held while
 * TSM is set, so the timers configured meanwhile start together when it is cleared). The harness
 * does: while TSM is set, clock-select writes to TCCR1B/TCCR3B are held back (the rest of the
 * register is written) and applied in the same cycle when TSM is cleared. The 32U4 firmware uses
 * it to run Timer3 in lock-step with Timer1.
 *
 * One fix to simavr 1.6's model, so that the firmware runs as on the chip: in the PWM modes the
 * ATmega's OCR1x registers are double-buffered and a written value takes effect at the next BOTTOM
 * (datasheet, "16-bit Timer/Counter1"); simavr 1.6 ignores OCR1x writes in fast PWM mode until the
 * timer is reconfigured. The harness applies a written OCR1A/OCR1B at the next overflow.
 *
 * A second fix: simavr 1.6 times UART bytes from UBRR alone when UBRR is written, so a firmware
 * that sets U2X afterwards (as this one does, like the Arduino core) gets half the baud rate, and
 * it counts a parity bit that is not configured: 187 us a byte instead of the chip's 85 us (117647
 * baud). The harness recomputes the byte time from UBRR, U2X, UCSZ, UPM and USBS whenever any of
 * them is written, so the pty carries bytes at the chip's rate.
 *
 * Two more, for Timer1 started and stopped by software, as the strawlab triggerbox firmware does
 * (firmware/strawlab_box): simavr 1.6 sets a "clear on match, set at BOTTOM" output (OC1A, OC1B)
 * when the clock is switched on or TCNT1 is written below the match, but on the chip such an
 * output is set only when the counter passes from TOP to BOTTOM: after a start from TCNT1 = 0 the
 * first rising edge is one period later. The harness leaves out of the edge log a rising edge
 * that simavr raises while a TCCR1B or TCNT1 write is under way. And simavr 1.6 reads TCNT1 as 0
 * while the clock is off and starts again from 0, where the chip's counter keeps its value while
 * stopped and goes on from it: the harness keeps the value when the clock goes off (and what is
 * written to TCNT1 meanwhile), reads it back while the clock is off, and restarts from it.
 */
#define _GNU_SOURCE
#include <errno.h>
#include <getopt.h>
#include <signal.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

#include "avr_ioport.h"
#include "avr_timer.h"
#include "sim_avr.h"
#include "sim_elf.h"
#include "sim_io.h"
#include "avr_uart.h"
#include <fcntl.h>
#include <poll.h>
#include <pty.h>
#include <sys/prctl.h>
#include <termios.h>

enum { SIG_TRIGGER = 0, SIG_PULSE0, SIG_OUT1, SIG_OUT2, SIG_OUT3, SIG_EVENT, SIG_COUNT };
static const char *const sig_names[SIG_COUNT] = {"trigger", "pulse0", "out1",
                                                 "out2",    "out3",   "event_in"};

typedef struct {
    char port;
    int bit;
} pin_t;

typedef struct {
    const char *mcu;
    pin_t pins[SIG_COUNT];
} board_t;

static const board_t boards[] = {
    {"atmega328p", {{'B', 1}, {'B', 2}, {'D', 4}, {'D', 5}, {'D', 6}, {'D', 2}}},
    /* 32U4 event input: ICP3 (PC7, D13), Timer3's input-capture pin */
    {"atmega32u4", {{'B', 5}, {'B', 6}, {'D', 4}, {'C', 6}, {'D', 7}, {'C', 7}}},
};

static avr_t *g_avr;
static avr_timer_t *g_t1;
static FILE *g_log;
static int g_level[SIG_COUNT];
static unsigned long long g_edges[SIG_COUNT];
static volatile sig_atomic_t g_stop;
/* Anything the firmware did that the outside sees (interrupt, pin edge, UART byte, injected edge):
 * an idle loop must not change it. */
static uint64_t g_activity;

/* OCR double-buffer model */
static int g_ocr_pending[AVR_TIMER_COMP_COUNT];
static struct {
    avr_io_write_t c;
    void *param;
} g_ocr_orig[AVR_TIMER_COMP_COUNT];

/* GTCCR.TSM model */
#define REG_GTCCR 0x43
#define REG_TCCR1B 0x81
#define REG_TCCR3B 0x91
#define TSM_BIT 7
static int g_tsm;
static struct {
    avr_io_write_t c;
    void *param;
    int pending;
    uint8_t value;
} g_tccrb[2]; /* 0: TCCR1B, 1: TCCR3B */
static avr_io_write_t g_gtccr_orig;
static void *g_gtccr_param;

static void tccrb_write(struct avr_t *avr, avr_io_addr_t addr, uint8_t v, void *param) {
    int i = (int)(intptr_t)param;
    if (g_tsm && (v & 7)) {
        g_tccrb[i].pending = 1;
        g_tccrb[i].value = v;
        v &= (uint8_t)~7;
    } else {
        g_tccrb[i].pending = 0;
    }
    g_tccrb[i].c(avr, addr, v, g_tccrb[i].param);
}

static void gtccr_write(struct avr_t *avr, avr_io_addr_t addr, uint8_t v, void *param) {
    (void)param;
    if (g_gtccr_orig)
        g_gtccr_orig(avr, addr, v, g_gtccr_param);
    else
        avr->data[addr] = v;
    if (v & (1 << TSM_BIT)) {
        g_tsm = 1;
        return;
    }
    g_tsm = 0; /* released: the held timers start now, in the same cycle */
    avr->data[addr] = v;
    for (int i = 0; i < 2; i++)
        if (g_tccrb[i].pending) {
            g_tccrb[i].pending = 0;
            g_tccrb[i].c(avr, i ? REG_TCCR3B : REG_TCCR1B, g_tccrb[i].value, g_tccrb[i].param);
        }
}

static void tsm_model_install(void) {
    static const avr_io_addr_t regs[2] = {REG_TCCR1B, REG_TCCR3B};
    for (int i = 0; i < 2; i++) {
        int io = AVR_DATA_TO_IO(regs[i]);
        if (!g_avr->io[io].w.c)
            return; /* no such timer on this core */
    }
    for (int i = 0; i < 2; i++) {
        int io = AVR_DATA_TO_IO(regs[i]);
        g_tccrb[i].c = g_avr->io[io].w.c;
        g_tccrb[i].param = g_avr->io[io].w.param;
        g_avr->io[io].w.c = tccrb_write;
        g_avr->io[io].w.param = (void *)(intptr_t)i;
    }
    int io = AVR_DATA_TO_IO(REG_GTCCR);
    g_gtccr_orig = g_avr->io[io].w.c;
    g_gtccr_param = g_avr->io[io].w.param;
    g_avr->io[io].w.c = gtccr_write;
    g_avr->io[io].w.param = NULL;
}

/* event input injection */
static avr_irq_t *g_event_irq;
static uint64_t g_ev_period, g_ev_phase, g_ev_high;

/* Interrupt entry. simavr 1.6 jumps to the vector in zero cycles; the AVR takes 4 (datasheet,
 * "Interrupt Response Time": PC pushed, I cleared, then the vector's jmp). The 4 cycles are added
 * here, so that an interrupt-timed value (the 328P event timestamp) lags as on the chip.
 * --irq-log: entries/exits as comment lines in the edge log (latency diagnosis). */
static int g_irq_log;
static void irq_hook(struct avr_irq_t *irq, uint32_t value, void *param) {
    int v = (int)(intptr_t)param;
    (void)irq;
    g_activity++;
    if (value)
        g_avr->cycle += 4;
    if (!g_irq_log)
        return;
    if (g_log && value) {
        /* the interrupted code's address, just pushed (high byte at SP+1) */
        uint16_t sp = (uint16_t)(g_avr->data[R_SPL] | (g_avr->data[R_SPH] << 8));
        unsigned ret = ((unsigned)g_avr->data[sp + 1] << 8 | g_avr->data[sp + 2]) * 2u;
        fprintf(g_log, "# irq %d enter %llu from=0x%x\n", v, (unsigned long long)g_avr->cycle, ret);
    } else if (g_log) {
        fprintf(g_log, "# irq %d exit %llu\n", v, (unsigned long long)g_avr->cycle);
    }
}

/* Timer1 started and stopped by software, as on the chip (see the header comment) */
static int g_t1_writing;   /* a TCCR1B or TCNT1 write is under way */
static uint16_t g_t1_hold; /* TCNT1 while the clock is off */
static struct {
    avr_io_write_t c;
    void *param;
} g_t1_cs_w, g_t1_tcnt_w;
static struct {
    avr_io_read_t c;
    void *param;
} g_t1_tcnt_r;

static int t1_clock_off(void) {
    return (g_avr->data[g_t1->cs[0].reg] & 7) == 0;
}

static uint16_t t1_data_tcnt(void) {
    return (uint16_t)(g_avr->data[g_t1->r_tcnt] | (g_avr->data[g_t1->r_tcnth] << 8));
}

static void t1_cs_write(struct avr_t *avr, avr_io_addr_t addr, uint8_t v, void *param) {
    (void)param;
    int was_off = t1_clock_off();
    if (!was_off && (v & 7) == 0) { /* stopping: the counter keeps its value */
        g_t1_tcnt_r.c(avr, g_t1->r_tcnt, g_t1_tcnt_r.param);
        g_t1_hold = t1_data_tcnt();
    }
    g_t1_writing++;
    if (g_t1_cs_w.c)
        g_t1_cs_w.c(avr, addr, v, g_t1_cs_w.param);
    else
        avr->data[addr] = v;
    if (was_off && !t1_clock_off() && g_t1_hold) { /* started again: from the kept value */
        avr->data[g_t1->r_tcnth] = (uint8_t)(g_t1_hold >> 8);
        avr->data[g_t1->r_tcnt] = (uint8_t)g_t1_hold;
        g_t1_tcnt_w.c(avr, g_t1->r_tcnt, (uint8_t)g_t1_hold, g_t1_tcnt_w.param);
    }
    g_t1_writing--;
}

static void t1_tcnt_write(struct avr_t *avr, avr_io_addr_t addr, uint8_t v, void *param) {
    (void)param;
    g_t1_writing++;
    g_t1_tcnt_w.c(avr, addr, v, g_t1_tcnt_w.param);
    g_t1_writing--;
    if (t1_clock_off())
        g_t1_hold = t1_data_tcnt();
}

static uint8_t t1_tcnt_read(struct avr_t *avr, avr_io_addr_t addr, void *param) {
    (void)param;
    if (!t1_clock_off())
        return g_t1_tcnt_r.c(avr, addr, g_t1_tcnt_r.param);
    avr->data[g_t1->r_tcnth] = (uint8_t)(g_t1_hold >> 8);
    avr->data[g_t1->r_tcnt] = (uint8_t)g_t1_hold;
    return avr->data[addr];
}

static void t1_start_stop_install(void) {
    int cs = AVR_DATA_TO_IO(g_t1->cs[0].reg), tc = AVR_DATA_TO_IO(g_t1->r_tcnt);
    if (!g_t1->r_tcnth || !g_avr->io[tc].w.c || !g_avr->io[tc].r.c)
        return;
    g_t1_cs_w.c = g_avr->io[cs].w.c;
    g_t1_cs_w.param = g_avr->io[cs].w.param;
    g_avr->io[cs].w.c = t1_cs_write;
    g_avr->io[cs].w.param = NULL;
    g_t1_tcnt_w.c = g_avr->io[tc].w.c;
    g_t1_tcnt_w.param = g_avr->io[tc].w.param;
    g_avr->io[tc].w.c = t1_tcnt_write;
    g_avr->io[tc].w.param = NULL;
    g_t1_tcnt_r.c = g_avr->io[tc].r.c;
    g_t1_tcnt_r.param = g_avr->io[tc].r.param;
    g_avr->io[tc].r.c = t1_tcnt_read;
    g_avr->io[tc].r.param = NULL;
}

static void on_signal(int s) {
    (void)s;
    g_stop = 1;
}

static avr_timer_t *find_timer(avr_t *avr, char name) {
    for (avr_io_t *io = avr->io_port; io; io = io->next)
        if (io->kind && strcmp(io->kind, "timer") == 0 && ((avr_timer_t *)io)->name == name)
            return (avr_timer_t *)io;
    return NULL;
}

static void log_edge(int sig, uint64_t cycle, int level) {
    if (g_level[sig] == level)
        return;
    g_level[sig] = level;
    g_edges[sig]++;
    if (g_log)
        fprintf(g_log, "%llu %s %d\n", (unsigned long long)cycle, sig_names[sig], level);
}

/* The cycle at which Timer1's hardware changed an OC1x pin: BOTTOM (tov_base) for a set, the
 * compare point for a clear. Falls back to the simulator's cycle if the two disagree by more than
 * an instruction's length (the pin was then driven by software through PORT). */
static uint64_t timer_edge_cycle(int comp, int level) {
    uint64_t now = g_avr->cycle, c;
    if (!g_t1 || !g_t1->tov_cycles)
        return now;
    c = level ? g_t1->tov_base : g_t1->tov_base + g_t1->comp[comp].comp_cycles;
    if (c > now || now - c > 8)
        return now;
    return c;
}

static void pin_hook(struct avr_irq_t *irq, uint32_t value, void *param) {
    int sig = (int)(intptr_t)param;
    int level = (value & 1) ? 1 : 0;
    uint64_t cycle = g_avr->cycle;
    (void)irq;
    g_activity++;
    /* simavr sets a PWM output when Timer1 is started; the chip only at the next BOTTOM */
    if (level && g_t1_writing && (sig == SIG_TRIGGER || sig == SIG_PULSE0))
        return;
    if (sig == SIG_TRIGGER)
        cycle = timer_edge_cycle(AVR_TIMER_COMPA, level);
    else if (sig == SIG_PULSE0)
        cycle = timer_edge_cycle(AVR_TIMER_COMPB, level);
    log_edge(sig, cycle, level);
}

static void ocr_write(struct avr_t *avr, avr_io_addr_t addr, uint8_t v, void *param) {
    int comp = (int)(intptr_t)param;
    g_ocr_orig[comp].c(avr, addr, v, g_ocr_orig[comp].param);
    g_ocr_pending[comp] = 1;
}

/* Runs when Timer1 raises its overflow (BOTTOM), before simavr schedules that frame's compare
 * events: the buffered OCR1x values take effect here, as on the chip. */
static void tov_hook(struct avr_irq_t *irq, uint32_t value, void *param) {
    (void)irq;
    (void)param;
    if (!value || !g_t1 || !g_t1->cs_div_value)
        return;
    for (int c = 0; c < AVR_TIMER_COMP_COUNT; c++) {
        if (!g_ocr_pending[c] || !g_t1->comp[c].r_ocr)
            continue;
        uint32_t ocr = g_avr->data[g_t1->comp[c].r_ocr];
        if (g_t1->comp[c].r_ocrh)
            ocr |= (uint32_t)g_avr->data[g_t1->comp[c].r_ocrh] << 8;
        g_t1->comp[c].comp_cycles =
            ocr <= g_t1->tov_top ? (uint64_t)g_t1->cs_div_value * (ocr + 1) : 0;
        g_ocr_pending[c] = 0;
    }
}

static avr_cycle_count_t event_tick(struct avr_t *avr, avr_cycle_count_t when, void *param) {
    int level = (int)(intptr_t)param;
    (void)avr;
    g_activity++;
    avr_raise_irq(g_event_irq, (uint32_t)level);
    log_edge(SIG_EVENT, g_avr->cycle, level);
    if (level) {
        avr_cycle_timer_register(g_avr, g_ev_high - (g_avr->cycle - when), event_tick,
                                 (void *)(intptr_t)0);
        return 0;
    }
    avr_cycle_timer_register(g_avr, g_ev_period - g_ev_high - (g_avr->cycle - when), event_tick,
                             (void *)(intptr_t)1);
    return 0;
}

/* UART byte time model (see the header comment) */
static avr_uart_t *g_uart;
static struct {
    avr_io_write_t c;
    void *param;
    avr_io_addr_t addr;
} g_uart_w[4];

static void uart_timing_update(void) {
    avr_uart_t *p = g_uart;
    uint8_t c = p->r_ucsrc ? g_avr->data[p->r_ucsrc] : 0x06;
    uint32_t ubrr = (uint32_t)(g_avr->data[p->ubrrl.reg] | (g_avr->data[p->ubrrh.reg] & 0x0F) << 8);
    int u2x = avr_regbit_get(g_avr, p->u2x);
    static const int databits[8] = {5, 6, 7, 8, 8, 8, 8, 9};
    int db = databits[((c >> 1) & 3) | (avr_regbit_get(g_avr, p->ucsz2) << 2)];
    int parity = ((c >> 4) & 3) ? 1 : 0; /* UPMn1:0 */
    int stop = (c & 0x08) ? 2 : 1;       /* USBSn */
    avr_cycle_count_t bit = (avr_cycle_count_t)(ubrr + 1) * (u2x ? 8 : 16);
    p->cycles_per_byte = bit * (avr_cycle_count_t)(1 + db + parity + stop);
}

static void uart_cfg_write(struct avr_t *avr, avr_io_addr_t addr, uint8_t v, void *param) {
    int i = (int)(intptr_t)param;
    if (g_uart_w[i].c)
        g_uart_w[i].c(avr, addr, v, g_uart_w[i].param);
    else
        avr->data[addr] = v;
    uart_timing_update();
}

static void uart_timing_install(char name) {
    for (avr_io_t *io = g_avr->io_port; io; io = io->next)
        if (io->kind && strcmp(io->kind, "uart") == 0 && ((avr_uart_t *)io)->name == name)
            g_uart = (avr_uart_t *)io;
    if (!g_uart)
        return;
    avr_io_addr_t regs[4] = {g_uart->r_ucsra, g_uart->r_ucsrc, g_uart->ubrrl.reg,
                             g_uart->ubrrh.reg};
    for (int i = 0; i < 4; i++) {
        if (!regs[i])
            continue;
        int io = AVR_DATA_TO_IO(regs[i]);
        g_uart_w[i].c = g_avr->io[io].w.c;
        g_uart_w[i].param = g_avr->io[io].w.param;
        g_uart_w[i].addr = regs[i];
        g_avr->io[io].w.c = uart_cfg_write;
        g_avr->io[io].w.param = (void *)(intptr_t)i;
    }
}

/* pty bridge: AVR UART <-> pty master, serviced from the main loop */
static int g_master = -1;
static avr_irq_t *g_uart_in;
static int g_xon = 1;
static uint8_t g_rx[512]; /* host -> AVR, waiting for the UART to accept */
static size_t g_rx_len, g_rx_done;
static uint8_t g_tx[4096];      /* AVR -> host, waiting for the pty */
static uint64_t g_tx_due[4096]; /* cycle at which each byte's stop bit ends */
static size_t g_tx_len;
static int g_paced;

static void uart_out_hook(struct avr_irq_t *irq, uint32_t value, void *param) {
    (void)irq;
    (void)param;
    g_activity++;
    if (g_tx_len < sizeof g_tx) {
        /* simavr raises the byte when UDR is written; the receiver has it one byte time later */
        g_tx_due[g_tx_len] = g_avr->cycle + (g_uart ? g_uart->cycles_per_byte : 0);
        g_tx[g_tx_len++] = (uint8_t)value;
    }
}
static void xon_hook(struct avr_irq_t *irq, uint32_t value, void *param) {
    (void)irq;
    (void)value;
    (void)param;
    g_xon = 1;
}
static void xoff_hook(struct avr_irq_t *irq, uint32_t value, void *param) {
    (void)irq;
    (void)value;
    (void)param;
    g_xon = 0;
}

/* Moves the bytes: out, those due by cycle `due` (all of them when not paced); in, what the pty
 * holds, at the current cycle. Returns the number of bytes given to the AVR. */
static size_t bridge_service(uint64_t due) {
    size_t n = 0, given = 0;
    while (n < g_tx_len && (!g_paced || g_tx_due[n] <= due))
        n++;
    if (n) {
        ssize_t w = write(g_master, g_tx, n);
        if (w > 0) {
            memmove(g_tx, g_tx + w, g_tx_len - (size_t)w);
            memmove(g_tx_due, g_tx_due + w, (g_tx_len - (size_t)w) * sizeof g_tx_due[0]);
            g_tx_len -= (size_t)w;
        }
    }
    if (g_rx_done == g_rx_len) {
        ssize_t r = read(g_master, g_rx, sizeof g_rx);
        g_rx_len = r > 0 ? (size_t)r : 0;
        g_rx_done = 0;
    }
    while (g_xon && g_rx_done < g_rx_len) {
        avr_raise_irq(g_uart_in, g_rx[g_rx_done++]);
        given++;
    }
    return given;
}

/* ------------------------------------------------------------------ idle-loop detection (paced) */
static uint8_t *g_snap;
static size_t g_snap_len;
static uint8_t g_snap_sreg[8];
static int8_t g_snap_istate;

static uint64_t next_timer_when(void) {
    avr_cycle_timer_slot_p t = g_avr->cycle_timers.timer;
    return t ? t->when : UINT64_MAX;
}

static void snap_take(void) {
    memcpy(g_snap, g_avr->data, g_snap_len);
    memcpy(g_snap_sreg, g_avr->sreg, sizeof g_snap_sreg);
    g_snap_istate = g_avr->interrupt_state;
}

static int snap_same(void) {
    return g_avr->interrupt_state == g_snap_istate &&
           memcmp(g_avr->sreg, g_snap_sreg, sizeof g_snap_sreg) == 0 &&
           memcmp(g_avr->data, g_snap, g_snap_len) == 0;
}

/* Emulates (at most max_cycles) until the firmware is back at an instruction with the whole state
 * as it was the last time there, no timer having fired and nothing seen outside: an idle loop.
 * Returns its length in cycles (the firmware is then at its start), or 0: busy, or the core
 * stopped (*state tells). */
static uint64_t find_idle_loop(uint64_t max_cycles, int *state) {
    *state = g_avr->state;
    if (g_avr->state != cpu_Running)
        return 0;
    const uint64_t start = g_avr->cycle;
    uint64_t c0 = start, when0 = next_timer_when(), act = g_activity;
    const avr_flashaddr_t pc0 = g_avr->pc;
    snap_take();
    while (g_avr->cycle - start < max_cycles) {
        *state = avr_run(g_avr);
        if (*state != cpu_Running)
            return 0;
        if (g_activity != act) {
            /* something happened: look for the loop from here on */
            act = g_activity;
            c0 = 0;
        }
        if (g_avr->pc != pc0)
            continue;
        if (c0 && g_avr->cycle < when0 && snap_same())
            return g_avr->cycle - c0;
        snap_take();
        c0 = g_avr->cycle;
        when0 = next_timer_when();
    }
    return 0;
}

/* Advances an idle firmware by whole loops to at most cycle `to`, staying before the next timer. */
static void skip_idle(uint64_t loop_len, uint64_t to) {
    uint64_t nt = next_timer_when();
    uint64_t lim = to < nt ? to : nt - 1;
    if (lim > g_avr->cycle)
        g_avr->cycle += (lim - g_avr->cycle) / loop_len * loop_len;
}

static int bridge_open(char uart, char *name, size_t name_len) {
    int m, s;
    char buf[128];
    struct termios tio;
    if (openpty(&m, &s, buf, NULL, NULL) < 0)
        return -1;
    tcgetattr(s, &tio);
    cfmakeraw(&tio);
    tcsetattr(s, TCSANOW, &tio);
    tcgetattr(m, &tio);
    cfmakeraw(&tio);
    tcsetattr(m, TCSANOW, &tio);
    fcntl(m, F_SETFL, fcntl(m, F_GETFL) | O_NONBLOCK);
    g_master = m; /* s stays open for the life of the process */
    snprintf(name, name_len, "%s", buf);
    uint32_t f = 0;
    avr_ioctl(g_avr, AVR_IOCTL_UART_GET_FLAGS(uart), &f);
    /* no console echo; no usleep() inside the simulation when the firmware polls UCSRA */
    f &= ~(uint32_t)(AVR_UART_FLAG_STDIO | AVR_UART_FLAG_POLL_SLEEP);
    avr_ioctl(g_avr, AVR_IOCTL_UART_SET_FLAGS(uart), &f);
    uart_timing_install(uart);
    g_uart_in = avr_io_getirq(g_avr, AVR_IOCTL_UART_GETIRQ(uart), UART_IRQ_INPUT);
    avr_irq_register_notify(avr_io_getirq(g_avr, AVR_IOCTL_UART_GETIRQ(uart), UART_IRQ_OUTPUT),
                            uart_out_hook, NULL);
    avr_irq_register_notify(avr_io_getirq(g_avr, AVR_IOCTL_UART_GETIRQ(uart), UART_IRQ_OUT_XON),
                            xon_hook, NULL);
    avr_irq_register_notify(avr_io_getirq(g_avr, AVR_IOCTL_UART_GETIRQ(uart), UART_IRQ_OUT_XOFF),
                            xoff_hook, NULL);
    return 0;
}

static double now_s(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + (double)ts.tv_nsec * 1e-9;
}

static void usage(const char *argv0) {
    fprintf(stderr,
            "usage: %s --elf FILE [--mcu atmega328p|atmega32u4] [--freq HZ] [--edges FILE]\n"
            "       [--pty-file FILE] [--realtime] [--max-seconds SIM_S] [--max-cycles N]\n"
            "       [--event-period CYCLES --event-phase CYCLES --event-high CYCLES] [--irq-log]\n"
            "       [--ppm P] [--drift-ppm-per-s D] [--help]\n",
            argv0);
}

/* The paced crystal: cycles due by wall time t (s after the start), and its inverse. */
static double g_ppm, g_drift; /* ppm, ppm per second */
static double cycles_at(double t, double freq) {
    return freq * (t + 1e-6 * (g_ppm * t + 0.5 * g_drift * t * t));
}
static double time_of(double c, double freq) {
    double a = 0.5e-6 * g_drift, b = 1.0 + 1e-6 * g_ppm, x = c / freq;
    if (a == 0.0)
        return x / b;
    return 2.0 * x / (b + sqrt(b * b + 4.0 * a * x)); /* the root of a t^2 + b t = x near x / b */
}

int main(int argc, char **argv) {
    const char *elf = NULL, *mcu = "atmega328p", *edges = NULL, *pty_file = NULL;
    unsigned long freq = 16000000UL;
    double max_seconds = 0;
    unsigned long long max_cycles = 0;
    int realtime = 0;
    static const struct option opts[] = {{"elf", required_argument, 0, 'e'},
                                         {"mcu", required_argument, 0, 'm'},
                                         {"freq", required_argument, 0, 'f'},
                                         {"edges", required_argument, 0, 'o'},
                                         {"pty-file", required_argument, 0, 'p'},
                                         {"realtime", no_argument, 0, 'r'},
                                         {"max-seconds", required_argument, 0, 's'},
                                         {"max-cycles", required_argument, 0, 'c'},
                                         {"event-period", required_argument, 0, 'P'},
                                         {"event-phase", required_argument, 0, 'H'},
                                         {"event-high", required_argument, 0, 'W'},
                                         {"help", no_argument, 0, 'h'},
                                         {"irq-log", no_argument, 0, 'I'},
                                         {"ppm", required_argument, 0, 'q'},
                                         {"drift-ppm-per-s", required_argument, 0, 'd'},
                                         {0, 0, 0, 0}};
    int o;
    while ((o = getopt_long(argc, argv, "", opts, NULL)) != -1) {
        switch (o) {
        case 'e':
            elf = optarg;
            break;
        case 'm':
            mcu = optarg;
            break;
        case 'f':
            freq = strtoul(optarg, NULL, 10);
            break;
        case 'o':
            edges = optarg;
            break;
        case 'p':
            pty_file = optarg;
            break;
        case 'r':
            realtime = 1;
            break;
        case 'q':
            g_ppm = strtod(optarg, NULL);
            break;
        case 'd':
            g_drift = strtod(optarg, NULL);
            break;
        case 's':
            max_seconds = strtod(optarg, NULL);
            break;
        case 'c':
            max_cycles = strtoull(optarg, NULL, 10);
            break;
        case 'P':
            g_ev_period = strtoull(optarg, NULL, 10);
            break;
        case 'H':
            g_ev_phase = strtoull(optarg, NULL, 10);
            break;
        case 'W':
            g_ev_high = strtoull(optarg, NULL, 10);
            break;
        case 'I':
            g_irq_log = 1;
            break;
        default:
            usage(argv[0]);
            return o == 'h' ? 0 : 2;
        }
    }
    if (!elf) {
        usage(argv[0]);
        return 2;
    }
    const board_t *board = NULL;
    for (size_t i = 0; i < sizeof boards / sizeof boards[0]; i++)
        if (strcmp(boards[i].mcu, mcu) == 0)
            board = &boards[i];
    if (!board) {
        fprintf(stderr, "error: unsupported --mcu %s (atmega328p or atmega32u4)\n", mcu);
        return 2;
    }
    if (g_ev_period && (g_ev_high == 0 || g_ev_high >= g_ev_period)) {
        fprintf(stderr, "error: --event-high must be in 1 .. --event-period - 1\n");
        return 2;
    }
    if (access(elf, R_OK) != 0) {
        fprintf(stderr, "error: cannot read firmware %s: %s\n", elf, strerror(errno));
        return 2;
    }

    elf_firmware_t fw;
    memset(&fw, 0, sizeof fw);
    if (elf_read_firmware(elf, &fw) != 0) {
        fprintf(stderr, "error: %s is not a loadable AVR ELF\n", elf);
        return 2;
    }
    g_avr = avr_make_mcu_by_name(mcu);
    if (!g_avr) {
        fprintf(stderr, "error: simavr has no core %s\n", mcu);
        return 2;
    }
    avr_init(g_avr);
    g_avr->log = LOG_ERROR;
    g_avr->frequency = (uint32_t)freq;
    avr_load_firmware(g_avr, &fw);
    g_avr->frequency = (uint32_t)freq; /* the ELF may carry none */

    g_t1 = find_timer(g_avr, '1');
    if (!g_t1) {
        fprintf(stderr, "error: no Timer1 in the %s core\n", mcu);
        return 2;
    }
    for (int c = 0; c < AVR_TIMER_COMP_COUNT; c++) {
        avr_io_addr_t a = g_t1->comp[c].r_ocr;
        if (!a)
            continue;
        int io = AVR_DATA_TO_IO(a);
        g_ocr_orig[c].c = g_avr->io[io].w.c;
        g_ocr_orig[c].param = g_avr->io[io].w.param;
        if (g_ocr_orig[c].c) {
            g_avr->io[io].w.c = ocr_write;
            g_avr->io[io].w.param = (void *)(intptr_t)c;
        }
    }
    avr_irq_register_notify(g_t1->overflow.irq + AVR_INT_IRQ_PENDING, tov_hook, NULL);
    if (find_timer(g_avr, '3'))
        tsm_model_install();
    t1_start_stop_install();

    if (edges) {
        g_log = fopen(edges, "w");
        if (!g_log) {
            fprintf(stderr, "error: cannot open edge log %s: %s\n", edges, strerror(errno));
            return 2;
        }
        setvbuf(g_log, NULL, _IOLBF, 0);
        fprintf(g_log, "# flytrack-trigger-sim 1 mcu=%s f_cpu=%lu\n# cycle signal level\n", mcu,
                freq);
    }
    for (int v = 0; v < g_avr->interrupts.vector_count; v++)
        if (g_avr->interrupts.vector[v])
            avr_irq_register_notify(g_avr->interrupts.vector[v]->irq + AVR_INT_IRQ_RUNNING,
                                    irq_hook,
                                    (void *)(intptr_t)g_avr->interrupts.vector[v]->vector);
    for (int s = 0; s < SIG_COUNT; s++) {
        g_level[s] = 0;
        avr_irq_t *irq =
            avr_io_getirq(g_avr, AVR_IOCTL_IOPORT_GETIRQ(board->pins[s].port), board->pins[s].bit);
        if (!irq) {
            fprintf(stderr, "error: no pin %c%d\n", board->pins[s].port, board->pins[s].bit);
            return 2;
        }
        if (s == SIG_EVENT)
            g_event_irq = irq;
        else
            avr_irq_register_notify(irq, pin_hook, (void *)(intptr_t)s);
    }
    /* The event input idles high (the firmware enables its pull-up; a photodiode pulls it low). */
    avr_raise_irq(g_event_irq, 1);
    g_level[SIG_EVENT] = 1;
    if (g_ev_period)
        avr_cycle_timer_register(g_avr, g_ev_phase ? g_ev_phase : g_ev_period, event_tick,
                                 (void *)(intptr_t)0);

    char pty_name[128];
    if (bridge_open(strcmp(mcu, "atmega32u4") == 0 ? '1' : '0', pty_name, sizeof pty_name) != 0) {
        fprintf(stderr, "error: cannot create a pty: %s\n", strerror(errno));
        return 2;
    }
    printf("PTY %s\n", pty_name);
    fflush(stdout);
    if (pty_file) {
        FILE *f = fopen(pty_file, "w");
        if (!f) {
            fprintf(stderr, "error: cannot write %s: %s\n", pty_file, strerror(errno));
            return 2;
        }
        fprintf(f, "%s\n", pty_name);
        fclose(f);
    }

    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    sigaction(SIGINT, &sa, NULL);
    sigaction(SIGTERM, &sa, NULL);
    signal(SIGPIPE, SIG_IGN);

    uint64_t limit = max_cycles;
    if (max_seconds > 0) {
        uint64_t c = (uint64_t)(max_seconds * (double)freq);
        if (!limit || c < limit)
            limit = c;
    }
    const double t0 = now_s();
    if (realtime && g_log) {
        /* The wall-clock anchor of the pacing: cycle c is due at t0 + c / f_cpu. CLOCK_REALTIME is
         * what a host stamps with (Python's time.time()), so edges can be placed on the host's
         * clock. */
        struct timespec rt;
        clock_gettime(CLOCK_REALTIME, &rt);
        fprintf(g_log, "# paced t0_monotonic=%.9f t0_realtime=%.9f ppm=%.6f drift_ppm_per_s=%.6f\n",
                t0, (double)rt.tv_sec + (double)rt.tv_nsec * 1e-9, g_ppm, g_drift);
    }
    int state = cpu_Running, rc = 0;
    if (!realtime) {
        /* Free running: host bytes are taken every 250 us of simulated time. */
        const uint64_t step = freq / 4000;
        uint64_t next_service = step;
        while (!g_stop) {
            state = avr_run(g_avr);
            if (state == cpu_Done || state == cpu_Crashed)
                break;
            if (limit && g_avr->cycle >= limit)
                break;
            if (g_avr->cycle < next_service)
                continue;
            next_service = g_avr->cycle + step;
            bridge_service(0);
        }
    } else {
        g_paced = 1;
        g_snap_len = (size_t)g_avr->ramend + 1;
        g_snap = malloc(g_snap_len);
        if (!g_snap) {
            fprintf(stderr, "error: out of memory\n");
            return 2;
        }
        prctl(PR_SET_TIMERSLACK, 1000UL);    /* wake within ~1 us of the asked time, not 50 us */
        const uint64_t ahead = freq / 20000; /* 50 us: how far a working firmware may run ahead */
        const uint64_t probe = 1000;         /* cycles a search for the idle loop may emulate */
        uint64_t loop_len = 0, probe_at = 0;
        while (!g_stop) {
            if (limit && g_avr->cycle >= limit)
                break;
            double now = now_s() - t0;
            uint64_t wall_c = now > 0 ? (uint64_t)cycles_at(now, (double)freq) : 0;
            if (limit && wall_c > limit)
                wall_c = limit;
            if (loop_len)
                skip_idle(loop_len, wall_c); /* catch up with the wall clock, never past it */
            if (bridge_service(wall_c))
                loop_len = 0; /* a host byte: the firmware has work */
            uint64_t wake_c;
            if (loop_len && next_timer_when() > wall_c) {
                /* idle: nothing happens before the next timer, a due byte or host input */
                wake_c = next_timer_when(); /* its edges then come at their time, not early */
            } else {
                loop_len = 0;
                uint64_t bound = wall_c + ahead;
                if (limit && bound > limit)
                    bound = limit;
                while (g_avr->cycle < bound && !loop_len) {
                    if (g_avr->cycle >= probe_at) {
                        loop_len = find_idle_loop(probe, &state);
                        if (!loop_len)
                            probe_at = g_avr->cycle + probe;
                    } else {
                        state = avr_run(g_avr);
                    }
                    if (state == cpu_Done || state == cpu_Crashed)
                        break;
                }
                if (state == cpu_Done || state == cpu_Crashed)
                    break;
                if (loop_len)
                    continue; /* idle again: catch up and sleep to the next timer */
                bridge_service(wall_c);
                wake_c = g_avr->cycle; /* working: let the wall clock catch up */
            }
            if (g_tx_len && g_tx_due[0] < wake_c)
                wake_c = g_tx_due[0];
            double wait = time_of((double)wake_c, (double)freq) - (now_s() - t0);
            if (wait > 2e-6) {
                if (wait > 0.5)
                    wait = 0.5;
                struct pollfd pfd = {g_master, POLLIN, 0};
                struct timespec ts = {(time_t)wait, (long)((wait - (double)(time_t)wait) * 1e9)};
                ppoll(&pfd, 1, &ts, NULL);
            }
        }
        free(g_snap);
    }
    if (state == cpu_Done || state == cpu_Crashed) {
        fprintf(stderr, "error: firmware stopped (state %d) at cycle %llu\n", state,
                (unsigned long long)g_avr->cycle);
        rc = 1;
    }
    double wall = now_s() - t0;
    g_paced = 0;
    bridge_service(0); /* last replies out */
    if (g_log)
        fclose(g_log);
    fprintf(stderr,
            "flytrack_trigger_sim: %llu cycles (%.3f s simulated) in %.3f s wall, %.1f MHz; "
            "trigger edges %llu, pulse0 edges %llu\n",
            (unsigned long long)g_avr->cycle, (double)g_avr->cycle / (double)freq, wall,
            wall > 0 ? (double)g_avr->cycle / wall / 1e6 : 0.0, g_edges[SIG_TRIGGER],
            g_edges[SIG_PULSE0]);
    return rc;
}
