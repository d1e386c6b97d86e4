/* flytrack_dvs_sim: runs the unchanged DVS bridge firmware (flytrack_dvs_sim.elf) in simavr and
 * plays a DVS sensor's AER bus on its pins.
 *
 * - The sensor: events from --events FILE (little-endian records of u32 earliest cycle, u16 address
 *   = byte 0 | byte 1 << 8 of the DVS word) are presented one at a time with the four-phase
 *   handshake: address on PB0..7 / PD0..6, then /REQ low (PD7 and PC7 = ICP3) at the event's cycle
 *   or --next-delay cycles after the previous /ACK release, whichever is later; /REQ goes high
 *   --req-delay cycles after the bridge pulls /ACK (PC6) low; the next event waits for /ACK high.
 *   Handshake violations (ACK without a request, ACK released before REQ) are counted and logged.
 * - The sync input: --sync-period/--sync-phase/--sync-high/--sync-count pulses on PE6 (INT6).
 * - USB: the bridge's simulator build talks through the usb_seam.h mailbox (GPIOR0..2), which this
 *   harness serves. It is a seam, not a USB model: bulk packets are collected as the firmware hands
 *   them over; the host drains --banks banks at one packet per --usb-packet-cycles (default 842 =
 *   19 packets per 1 ms frame, full-speed bulk's ceiling); vendor requests come from --control FILE
 *   (lines "<cycle> <8-byte setup hex> [OUT data hex]", delivered in order, each at or after its
 *   cycle once the previous one was answered).
 * - --out FILE gets one line per observation (cycle = CPU cycle since reset):
 *       # flytrack-dvs-sim 1 f_cpu=<hz>
 *       req <index> <cycle>                /REQ asserted for event <index> (the truth time)
 *       bulk <cycle> <hex>                 a bulk-IN packet as handed to the host
 *       ctrl <cycle> <bRequest> ok <hex>   a request's reply (IN data, may be empty) | stall
 *       sync <cycle>                       a sync pulse's rising edge
 *       timer <cycle> <tccr3b> <tcnt3>     Timer3's clock or count written (TCCR3B / TCNT3): with
 *                                          a clock running, the count is tcnt3 at that cycle
 *       bias <hex>                         the bits shifted into the bias register at a latch
 *       array_reset <cycle>
 *       violation <cycle> <what>
 *       end <cycle> played=<n> first_req=<c> last_ack=<c> violations=<n> packets=<n> pc=<byte addr>
 * - An interrupt's entry costs 4 cycles, as on the chip (simavr 1.6 charges none).
 * - An input capture of TOP + 1 (simavr's lazy CTC reset, see icr_read) reads as 0, as on the chip.
 * The run ends once every event and request is done and no packet came for --drain-cycles, or at
 * --max-cycles.
 */
#define _GNU_SOURCE
#include <errno.h>
#include <getopt.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

#include "avr_ioport.h"
#include "sim_avr.h"
#include "sim_elf.h"
#include "sim_io.h"
#include "sim_cycle_timers.h"

#define REG_GPIOR0 0x3E
#define REG_GPIOR1 0x4A
#define REG_GPIOR2 0x4B
#define REG_TCCR3B 0x91
#define REG_TCNT3L 0x94
#define REG_TCNT3H 0x95

static avr_t *g_avr;
static FILE *g_out;

/* ---- sensor */
typedef struct {
    uint32_t cycle;
    uint16_t addr;
} ev_t;
static ev_t *g_ev;
static size_t g_nev, g_next;
static enum { S_IDLE, S_REQ, S_RELEASED } g_state = S_IDLE;
static uint64_t g_req_delay = 2, g_next_delay = 2;
static uint64_t g_last_ack_rel, g_first_req, g_last_ack;
static int g_scheduled;
static unsigned long g_violations;
static avr_irq_t *g_pb[8], *g_pd[8], *g_pc7, *g_pe6;

static void violation(const char *what) {
    g_violations++;
    fprintf(g_out, "violation %llu %s\n", (unsigned long long)g_avr->cycle, what);
}

static avr_cycle_count_t present(struct avr_t *avr, avr_cycle_count_t when, void *param) {
    (void)avr;
    (void)when;
    (void)param;
    g_scheduled = 0;
    uint16_t a = g_ev[g_next].addr;
    for (int b = 0; b < 8; b++)
        avr_raise_irq(g_pb[b], (a >> b) & 1);
    for (int b = 0; b < 7; b++)
        avr_raise_irq(g_pd[b], (a >> (8 + b)) & 1);
    /* address first, then /REQ on both of its pins */
    avr_raise_irq(g_pd[7], 0);
    avr_raise_irq(g_pc7, 0);
    if (!g_next)
        g_first_req = g_avr->cycle;
    fprintf(g_out, "req %zu %llu\n", g_next, (unsigned long long)g_avr->cycle);
    g_state = S_REQ;
    return 0;
}

static void schedule_next(void) {
    if (g_next >= g_nev || g_scheduled)
        return;
    uint64_t at = g_last_ack_rel + g_next_delay;
    if (g_ev[g_next].cycle > at)
        at = g_ev[g_next].cycle;
    uint64_t now = g_avr->cycle;
    g_scheduled = 1;
    avr_cycle_timer_register(g_avr, at > now ? at - now : 1, present, NULL);
}

static avr_cycle_count_t release_req(struct avr_t *avr, avr_cycle_count_t when, void *param) {
    (void)avr;
    (void)when;
    (void)param;
    avr_raise_irq(g_pd[7], 1);
    avr_raise_irq(g_pc7, 1);
    g_state = S_RELEASED;
    return 0;
}

static int g_ack_level = -1;
static void ack_hook(struct avr_irq_t *irq, uint32_t value, void *param) {
    (void)irq;
    (void)param;
    int level = value & 1;
    if (level == g_ack_level)
        return;
    int was = g_ack_level;
    g_ack_level = level;
    if (was < 0)
        return; /* the firmware setting up its pin */
    if (!level) {
        if (g_state != S_REQ) {
            violation("ack_without_request");
            return;
        }
        avr_cycle_timer_register(g_avr, g_req_delay, release_req, NULL);
    } else {
        if (g_state != S_RELEASED) {
            if (g_state == S_REQ)
                violation("ack_released_before_req");
            return;
        }
        g_state = S_IDLE;
        g_last_ack_rel = g_last_ack = g_avr->cycle;
        g_next++;
        schedule_next();
    }
}

/* ---- sync pulses */
static uint64_t g_sync_period, g_sync_phase, g_sync_high, g_sync_count, g_sync_sent;
static avr_cycle_count_t sync_tick(struct avr_t *avr, avr_cycle_count_t when, void *param) {
    (void)avr;
    int level = (int)(intptr_t)param;
    avr_raise_irq(g_pe6, (uint32_t)level);
    if (level) {
        fprintf(g_out, "sync %llu\n", (unsigned long long)g_avr->cycle);
        g_sync_sent++;
        avr_cycle_timer_register(g_avr, g_sync_high - (g_avr->cycle - when), sync_tick,
                                 (void *)(intptr_t)0);
    } else if (g_sync_sent < g_sync_count) {
        avr_cycle_timer_register(g_avr, g_sync_period - g_sync_high - (g_avr->cycle - when),
                                 sync_tick, (void *)(intptr_t)1);
    }
    return 0;
}

/* ---- USB seam mailbox */
static uint8_t g_pkt[256];
static size_t g_pkt_len;
static int g_banks_free = 2;
static uint64_t g_usb_packet_cycles = 842, g_host_busy_until;
static unsigned long g_packets;
static uint64_t g_last_packet;

typedef struct {
    uint64_t cycle;
    uint8_t bytes[8 + 256];
    size_t len;
} ctrl_t;
static ctrl_t *g_ctrl;
static size_t g_nctrl, g_cur_ctrl, g_ctrl_pos;
static int g_ctrl_active;
static uint8_t g_reply[256];
static size_t g_reply_len;

static void status_update(void) {
    g_avr->data[REG_GPIOR0] = (uint8_t)((g_banks_free > 0 ? 1 : 0) | (g_ctrl_active ? 2 : 0));
}

static avr_cycle_count_t bank_freed(struct avr_t *avr, avr_cycle_count_t when, void *param) {
    (void)avr;
    (void)when;
    (void)param;
    g_banks_free++;
    status_update();
    return 0;
}

static void data_write(struct avr_t *avr, avr_io_addr_t addr, uint8_t v, void *param) {
    (void)avr;
    (void)addr;
    (void)param;
    if (g_pkt_len < sizeof g_pkt)
        g_pkt[g_pkt_len++] = v;
}

static uint8_t data_read(struct avr_t *avr, avr_io_addr_t addr, void *param) {
    (void)avr;
    (void)addr;
    (void)param;
    if (!g_ctrl_active || g_ctrl_pos >= g_ctrl[g_cur_ctrl].len) {
        violation("request_byte_read_past_end");
        return 0;
    }
    return g_ctrl[g_cur_ctrl].bytes[g_ctrl_pos++];
}

static void reply_write(struct avr_t *avr, avr_io_addr_t addr, uint8_t v, void *param) {
    (void)avr;
    (void)addr;
    (void)param;
    if (g_reply_len < sizeof g_reply)
        g_reply[g_reply_len++] = v;
    status_update(); /* the register keeps the harness's status, not the written byte */
}

static avr_cycle_count_t ctrl_due(struct avr_t *avr, avr_cycle_count_t when, void *param);

static void ctrl_next(void) {
    if (g_cur_ctrl >= g_nctrl)
        return;
    uint64_t now = g_avr->cycle, at = g_ctrl[g_cur_ctrl].cycle;
    avr_cycle_timer_register(g_avr, at > now ? at - now : 1, ctrl_due, NULL);
}

static avr_cycle_count_t ctrl_due(struct avr_t *avr, avr_cycle_count_t when, void *param) {
    (void)avr;
    (void)when;
    (void)param;
    g_ctrl_active = 1;
    g_ctrl_pos = 0;
    g_reply_len = 0;
    status_update();
    return 0;
}

static void cmd_write(struct avr_t *avr, avr_io_addr_t addr, uint8_t v, void *param) {
    (void)param;
    avr->data[addr] = v;
    uint64_t now = g_avr->cycle;
    if (v == 1) { /* SEND */
        if (g_banks_free <= 0)
            violation("send_without_free_bank");
        if (g_pkt_len > 64)
            violation("packet_over_64_bytes");
        fprintf(g_out, "bulk %llu ", (unsigned long long)now);
        for (size_t i = 0; i < g_pkt_len; i++)
            fprintf(g_out, "%02x", g_pkt[i]);
        fputc('\n', g_out);
        g_pkt_len = 0;
        g_packets++;
        g_last_packet = now;
        g_banks_free--;
        uint64_t start = g_host_busy_until > now ? g_host_busy_until : now;
        g_host_busy_until = start + g_usb_packet_cycles;
        /* one timer per bank in flight (simavr keeps one timer per callback and param) */
        avr_cycle_timer_register(g_avr, g_host_busy_until - now ? g_host_busy_until - now : 1,
                                 bank_freed, (void *)(intptr_t)(1 + g_packets % 64));
    } else if (v == 2 || v == 3) { /* REPLY / STALL */
        if (!g_ctrl_active) {
            violation("reply_without_request");
            return;
        }
        fprintf(g_out, "ctrl %llu %02x %s ", (unsigned long long)now, g_ctrl[g_cur_ctrl].bytes[1],
                v == 2 ? "ok" : "stall");
        for (size_t i = 0; i < g_reply_len; i++)
            fprintf(g_out, "%02x", g_reply[i]);
        fputc('\n', g_out);
        g_ctrl_active = 0;
        g_cur_ctrl++;
        ctrl_next();
    } else {
        violation("unknown_command");
    }
    status_update();
}

/* ---- Timer3 (re)starts: the epoch of the firmware's timestamps */
static avr_io_write_t g_tccr_orig, g_tcnt_orig;
static void *g_tccr_param, *g_tcnt_param;
static void tccr_write(struct avr_t *avr, avr_io_addr_t addr, uint8_t v, void *param) {
    (void)param;
    g_tccr_orig(avr, addr, v, g_tccr_param);
    fprintf(g_out, "timer %llu %u %u\n", (unsigned long long)g_avr->cycle, v,
            (unsigned)(avr->data[REG_TCNT3L] | avr->data[REG_TCNT3H] << 8));
}
/* simavr 1.6 resets a CTC timer lazily (a cycle timer run after the instruction under way), so an
 * input capture in the wrap's own cycle can read TOP + 1, which the chip never holds: the count
 * goes TOP -> 0. The harness reads such a capture as 0, as the chip would have captured it. */
#define REG_ICR3L 0x96
#define REG_ICR3H 0x97
#define REG_OCR3AL 0x98
#define REG_OCR3AH 0x99
static unsigned long g_icr_fixed;
static uint8_t icr_read(struct avr_t *avr, avr_io_addr_t addr, void *param) {
    (void)param;
    unsigned icr = avr->data[REG_ICR3L] | avr->data[REG_ICR3H] << 8;
    unsigned top = avr->data[REG_OCR3AL] | avr->data[REG_OCR3AH] << 8;
    if ((avr->data[REG_TCCR3B] & 0x18) == 0x08 && icr == top + 1) { /* CTC mode 4 */
        avr->data[REG_ICR3L] = avr->data[REG_ICR3H] = 0;
        g_icr_fixed++;
    }
    return avr->data[addr];
}

static void tcnt_write(struct avr_t *avr, avr_io_addr_t addr, uint8_t v, void *param) {
    (void)param;
    g_tcnt_orig(avr, addr, v, g_tcnt_param);
    fprintf(g_out, "timer %llu %u %u\n", (unsigned long long)g_avr->cycle, avr->data[REG_TCCR3B],
            (unsigned)(v | avr->data[REG_TCNT3H] << 8));
}

/* ---- bias shift register and array reset on port F */
static int g_bias_bit;
static uint8_t g_bias[64];
static size_t g_bias_bits;
static void portf_hook(struct avr_irq_t *irq, uint32_t value, void *param) {
    (void)irq;
    int pin = (int)(intptr_t)param;
    int level = value & 1;
    if (pin == 5) {
        g_bias_bit = level;
    } else if (pin == 4 && level) {
        if (g_bias_bits < sizeof g_bias * 8) {
            if (g_bias_bits % 8 == 0)
                g_bias[g_bias_bits / 8] = 0;
            g_bias[g_bias_bits / 8] |= (uint8_t)(g_bias_bit << (7 - g_bias_bits % 8));
        }
        g_bias_bits++;
    } else if (pin == 6 && level) {
        fprintf(g_out, "bias ");
        for (size_t i = 0; i < (g_bias_bits + 7) / 8 && i < sizeof g_bias; i++)
            fprintf(g_out, "%02x", g_bias[i]);
        fputc('\n', g_out);
        g_bias_bits = 0;
    } else if (pin == 7 && level) {
        fprintf(g_out, "array_reset %llu\n", (unsigned long long)g_avr->cycle);
    }
}

static void irq_hook(struct avr_irq_t *irq, uint32_t value, void *param) {
    (void)irq;
    (void)param;
    if (value)
        g_avr->cycle += 4;
}

static int hexval(int c) {
    if (c >= '0' && c <= '9')
        return c - '0';
    if (c >= 'a' && c <= 'f')
        return c - 'a' + 10;
    if (c >= 'A' && c <= 'F')
        return c - 'A' + 10;
    return -1;
}

static int load_control(const char *path) {
    FILE *f = fopen(path, "r");
    char line[1200];
    size_t cap = 0, lineno = 0;
    if (!f) {
        fprintf(stderr, "error: cannot read %s: %s\n", path, strerror(errno));
        return -1;
    }
    while (fgets(line, sizeof line, f)) {
        lineno++;
        char *p = line, *end;
        while (*p == ' ')
            p++;
        if (*p == '#' || *p == '\n' || !*p)
            continue;
        if (g_nctrl == cap) {
            cap = cap ? cap * 2 : 16;
            g_ctrl = realloc(g_ctrl, cap * sizeof *g_ctrl);
        }
        ctrl_t *c = &g_ctrl[g_nctrl];
        c->cycle = strtoull(p, &end, 10);
        c->len = 0;
        for (p = end; *p && *p != '\n'; p++) {
            if (*p == ' ')
                continue;
            int hi = hexval(p[0]), lo = hexval(p[1]);
            if (hi < 0 || lo < 0 || c->len >= sizeof c->bytes) {
                fprintf(stderr, "error: %s:%zu: bad hex\n", path, lineno);
                fclose(f);
                return -1;
            }
            c->bytes[c->len++] = (uint8_t)(hi << 4 | lo);
            p++;
        }
        if (c->len < 8) {
            fprintf(stderr, "error: %s:%zu: a request needs its 8 setup bytes\n", path, lineno);
            fclose(f);
            return -1;
        }
        g_nctrl++;
    }
    fclose(f);
    return 0;
}

static int load_events(const char *path) {
    FILE *f = fopen(path, "rb");
    if (!f) {
        fprintf(stderr, "error: cannot read %s: %s\n", path, strerror(errno));
        return -1;
    }
    fseek(f, 0, SEEK_END);
    long n = ftell(f);
    fseek(f, 0, SEEK_SET);
    if (n < 0 || n % 6) {
        fprintf(stderr, "error: %s: size %ld is not a whole number of 6-byte records\n", path, n);
        fclose(f);
        return -1;
    }
    g_nev = (size_t)n / 6;
    g_ev = calloc(g_nev ? g_nev : 1, sizeof *g_ev);
    for (size_t i = 0; i < g_nev; i++) {
        uint8_t r[6];
        if (fread(r, 1, 6, f) != 6) {
            fclose(f);
            return -1;
        }
        g_ev[i].cycle = (uint32_t)(r[0] | r[1] << 8 | r[2] << 16 | (uint32_t)r[3] << 24);
        g_ev[i].addr = (uint16_t)(r[4] | r[5] << 8);
    }
    fclose(f);
    return 0;
}

static void usage(const char *argv0) {
    fprintf(
        stderr,
        "usage: %s --elf FILE --out FILE [--events FILE] [--control FILE] [--freq HZ]\n"
        "       [--req-delay CYCLES] [--next-delay CYCLES] [--usb-packet-cycles N] [--banks N]\n"
        "       [--sync-period CYCLES --sync-phase CYCLES --sync-high CYCLES --sync-count N]\n"
        "       [--drain-cycles N] [--max-cycles N] [--help]\n",
        argv0);
}

int main(int argc, char **argv) {
    const char *elf = NULL, *out = NULL, *events = NULL, *control = NULL;
    unsigned long freq = 16000000UL;
    uint64_t max_cycles = 2000000000ULL, drain_cycles = 160000;
    static const struct option opts[] = {{"elf", required_argument, 0, 'e'},
                                         {"out", required_argument, 0, 'o'},
                                         {"events", required_argument, 0, 'v'},
                                         {"control", required_argument, 0, 'c'},
                                         {"freq", required_argument, 0, 'f'},
                                         {"req-delay", required_argument, 0, 'r'},
                                         {"next-delay", required_argument, 0, 'n'},
                                         {"usb-packet-cycles", required_argument, 0, 'u'},
                                         {"banks", required_argument, 0, 'b'},
                                         {"sync-period", required_argument, 0, 'P'},
                                         {"sync-phase", required_argument, 0, 'H'},
                                         {"sync-high", required_argument, 0, 'W'},
                                         {"sync-count", required_argument, 0, 'N'},
                                         {"drain-cycles", required_argument, 0, 'd'},
                                         {"max-cycles", required_argument, 0, 'm'},
                                         {"help", no_argument, 0, 'h'},
                                         {0, 0, 0, 0}};
    int o;
    while ((o = getopt_long(argc, argv, "", opts, NULL)) != -1) {
        switch (o) {
        case 'e':
            elf = optarg;
            break;
        case 'o':
            out = optarg;
            break;
        case 'v':
            events = optarg;
            break;
        case 'c':
            control = optarg;
            break;
        case 'f':
            freq = strtoul(optarg, NULL, 10);
            break;
        case 'r':
            g_req_delay = strtoull(optarg, NULL, 10);
            break;
        case 'n':
            g_next_delay = strtoull(optarg, NULL, 10);
            break;
        case 'u':
            g_usb_packet_cycles = strtoull(optarg, NULL, 10);
            break;
        case 'b':
            g_banks_free = atoi(optarg);
            break;
        case 'P':
            g_sync_period = strtoull(optarg, NULL, 10);
            break;
        case 'H':
            g_sync_phase = strtoull(optarg, NULL, 10);
            break;
        case 'W':
            g_sync_high = strtoull(optarg, NULL, 10);
            break;
        case 'N':
            g_sync_count = strtoull(optarg, NULL, 10);
            break;
        case 'd':
            drain_cycles = strtoull(optarg, NULL, 10);
            break;
        case 'm':
            max_cycles = strtoull(optarg, NULL, 10);
            break;
        default:
            usage(argv[0]);
            return o == 'h' ? 0 : 2;
        }
    }
    if (!elf || !out) {
        usage(argv[0]);
        return 2;
    }
    if (g_req_delay < 1 || g_next_delay < 1 || g_banks_free < 1) {
        fprintf(stderr, "error: --req-delay, --next-delay and --banks must be at least 1\n");
        return 2;
    }
    if (g_sync_count && (!g_sync_period || !g_sync_high || g_sync_high >= g_sync_period)) {
        fprintf(stderr, "error: --sync-high must be in 1 .. --sync-period - 1\n");
        return 2;
    }
    if (events && load_events(events) != 0)
        return 2;
    if (control && load_control(control) != 0)
        return 2;
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
    g_avr = avr_make_mcu_by_name("atmega32u4");
    if (!g_avr) {
        fprintf(stderr, "error: simavr has no atmega32u4 core\n");
        return 2;
    }
    avr_init(g_avr);
    g_avr->log = LOG_ERROR;
    avr_load_firmware(g_avr, &fw);
    g_avr->frequency = (uint32_t)freq;
    g_out = fopen(out, "w");
    if (!g_out) {
        fprintf(stderr, "error: cannot open %s: %s\n", out, strerror(errno));
        return 2;
    }
    fprintf(g_out, "# flytrack-dvs-sim 1 f_cpu=%lu\n", freq);

    for (int b = 0; b < 8; b++) {
        g_pb[b] = avr_io_getirq(g_avr, AVR_IOCTL_IOPORT_GETIRQ('B'), b);
        g_pd[b] = avr_io_getirq(g_avr, AVR_IOCTL_IOPORT_GETIRQ('D'), b);
    }
    g_pc7 = avr_io_getirq(g_avr, AVR_IOCTL_IOPORT_GETIRQ('C'), 7);
    g_pe6 = avr_io_getirq(g_avr, AVR_IOCTL_IOPORT_GETIRQ('E'), 6);
    avr_irq_register_notify(avr_io_getirq(g_avr, AVR_IOCTL_IOPORT_GETIRQ('C'), 6), ack_hook, NULL);
    for (int b = 4; b < 8; b++)
        avr_irq_register_notify(avr_io_getirq(g_avr, AVR_IOCTL_IOPORT_GETIRQ('F'), b), portf_hook,
                                (void *)(intptr_t)b);
    for (int v = 0; v < g_avr->interrupts.vector_count; v++)
        if (g_avr->interrupts.vector[v])
            avr_irq_register_notify(g_avr->interrupts.vector[v]->irq + AVR_INT_IRQ_RUNNING,
                                    irq_hook, NULL);
    /* idle bus: /REQ high, sync low */
    avr_raise_irq(g_pd[7], 1);
    avr_raise_irq(g_pc7, 1);
    avr_raise_irq(g_pe6, 0);

    avr_register_io_write(g_avr, REG_GPIOR1, data_write, NULL);
    avr_register_io_read(g_avr, REG_GPIOR1, data_read, NULL);
    avr_register_io_write(g_avr, REG_GPIOR0, reply_write, NULL);
    avr_register_io_write(g_avr, REG_GPIOR2, cmd_write, NULL);
    avr_register_io_read(g_avr, REG_ICR3L, icr_read, NULL);
    {
        int io = AVR_DATA_TO_IO(REG_TCCR3B);
        g_tccr_orig = g_avr->io[io].w.c;
        g_tccr_param = g_avr->io[io].w.param;
        g_avr->io[io].w.c = tccr_write;
        io = AVR_DATA_TO_IO(REG_TCNT3L);
        g_tcnt_orig = g_avr->io[io].w.c;
        g_tcnt_param = g_avr->io[io].w.param;
        if (!g_tccr_orig || !g_tcnt_orig) {
            fprintf(stderr, "error: simavr's atmega32u4 core has no Timer3\n");
            return 2;
        }
        g_avr->io[io].w.c = tcnt_write;
    }
    status_update();
    if (g_sync_count)
        avr_cycle_timer_register(g_avr, g_sync_phase ? g_sync_phase : g_sync_period, sync_tick,
                                 (void *)(intptr_t)1);
    ctrl_next();
    schedule_next();

    struct timespec t0, t1;
    clock_gettime(CLOCK_MONOTONIC, &t0);
    int state = cpu_Running, rc = 0;
    while (g_avr->cycle < max_cycles) {
        state = avr_run(g_avr);
        if (state == cpu_Done || state == cpu_Crashed)
            break;
        if (g_next >= g_nev && g_cur_ctrl >= g_nctrl && g_sync_sent >= g_sync_count &&
            g_avr->cycle > g_last_packet + drain_cycles && g_avr->cycle > g_last_ack + drain_cycles)
            break;
    }
    clock_gettime(CLOCK_MONOTONIC, &t1);
    if (state == cpu_Done || state == cpu_Crashed) {
        fprintf(stderr, "error: firmware stopped (state %d) at cycle %llu\n", state,
                (unsigned long long)g_avr->cycle);
        rc = 1;
    }
    fprintf(g_out,
            "end %llu played=%zu first_req=%llu last_ack=%llu violations=%lu packets=%lu pc=%u\n",
            (unsigned long long)g_avr->cycle, g_next, (unsigned long long)g_first_req,
            (unsigned long long)g_last_ack, g_violations, g_packets, (unsigned)g_avr->pc);
    fclose(g_out);
    double wall = (double)(t1.tv_sec - t0.tv_sec) + (double)(t1.tv_nsec - t0.tv_nsec) * 1e-9;
    fprintf(
        stderr, "flytrack_dvs_sim: %llu cycles (%.3f s simulated) in %.3f s wall; %zu/%zu events\n",
        (unsigned long long)g_avr->cycle, (double)g_avr->cycle / (double)freq, wall, g_next, g_nev);
    if (g_next < g_nev) {
        fprintf(stderr, "error: %zu events never handshaken (max cycles reached)\n",
                g_nev - g_next);
        rc = rc ? rc : 1;
    }
    return rc;
}
