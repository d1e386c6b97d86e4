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
 *   time); otherwise it runs as fast as it can.
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
 */
#define _GNU_SOURCE
#include <errno.h>
#include <getopt.h>
#include <signal.h>
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

/* pty bridge: AVR UART <-> pty master, serviced from the main loop */
static int g_master = -1;
static avr_irq_t *g_uart_in;
static int g_xon = 1;
static uint8_t g_rx[512]; /* host -> AVR, waiting for the UART to accept */
static size_t g_rx_len, g_rx_done;
static uint8_t g_tx[4096]; /* AVR -> host, waiting for the pty */
static size_t g_tx_len;

static void uart_out_hook(struct avr_irq_t *irq, uint32_t value, void *param) {
    (void)irq;
    (void)param;
    if (g_tx_len < sizeof g_tx)
        g_tx[g_tx_len++] = (uint8_t)value;
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

static void bridge_service(void) {
    if (g_tx_len) {
        ssize_t w = write(g_master, g_tx, g_tx_len);
        if (w > 0) {
            memmove(g_tx, g_tx + w, g_tx_len - (size_t)w);
            g_tx_len -= (size_t)w;
        }
    }
    if (g_rx_done == g_rx_len) {
        ssize_t r = read(g_master, g_rx, sizeof g_rx);
        g_rx_len = r > 0 ? (size_t)r : 0;
        g_rx_done = 0;
    }
    while (g_xon && g_rx_done < g_rx_len)
        avr_raise_irq(g_uart_in, g_rx[g_rx_done++]);
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
    f &= ~AVR_UART_FLAG_STDIO;
    avr_ioctl(g_avr, AVR_IOCTL_UART_SET_FLAGS(uart), &f);
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
            "       [--event-period CYCLES --event-phase CYCLES --event-high CYCLES]\n",
            argv0);
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
    /* Host bytes are taken every 50 us of simulated time when paced (a wait for the wall clock is a
     * ppoll on the pty, so a request arriving then is taken at once), every 250 us when free. */
    const uint64_t step = realtime ? freq / 20000 : freq / 4000;
    uint64_t next_service = step;
    int state = cpu_Running, rc = 0;
    while (!g_stop) {
        state = avr_run(g_avr);
        if (state == cpu_Done || state == cpu_Crashed) {
            fprintf(stderr, "error: firmware stopped (state %d) at cycle %llu\n", state,
                    (unsigned long long)g_avr->cycle);
            rc = 1;
            break;
        }
        if (limit && g_avr->cycle >= limit)
            break;
        if (g_avr->cycle < next_service)
            continue;
        next_service = g_avr->cycle + step;
        if (realtime) {
            double ahead = (double)g_avr->cycle / (double)freq - (now_s() - t0);
            if (ahead > 20e-6 && g_rx_done == g_rx_len) {
                struct pollfd pfd = {g_master, POLLIN, 0};
                struct timespec ts = {(time_t)ahead, (long)((ahead - (double)(time_t)ahead) * 1e9)};
                ppoll(&pfd, 1, &ts, NULL);
            }
        }
        bridge_service();
    }
    double wall = now_s() - t0;
    bridge_service(); /* last replies out */
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
