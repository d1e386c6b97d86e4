/* Fuzz test of the event-file readers, built with ASan + UBSan (abort on any finding).
 *
 * fuzz_events [iterations]: fixed seed. Seeds are small valid files of every format (AEDAT 4.0 in
 * all three compressions and EVT 3.0 from the writers, the others built here); inputs are bit
 * flips, byte overwrites, truncations, 32-bit fields set to extremes, and spliced copies, read
 * with both format detection and every explicit format, with random read sizes. Oracles beyond
 * "no crash, no UB, no read outside the input": a failed reader names an offset within the input;
 * a truncated copy of a valid file returns, before its error, exactly the leading events of the
 * whole file (nothing before the damage is lost, nothing invented). */
#define _POSIX_C_SOURCE 200809L
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "flytrack/events.h"

static uint64_t rng = 0x2545F4914F6CDD1Dull;
static uint64_t rnd(void) {
    rng ^= rng >> 12;
    rng ^= rng << 25;
    rng ^= rng >> 27;
    return rng * 2685821657736338717ull;
}
static size_t below(size_t n) {
    return n ? (size_t)(rnd() % n) : 0;
}

#define MAXF (1 << 16)
typedef struct {
    uint8_t b[MAXF];
    size_t n;
    int fmt;
    const char *name;
} seed;
static seed seeds[16];
static size_t n_seeds;
static int failures;

static void put(seed *s, const void *p, size_t n) {
    if (s->n + n <= MAXF) {
        memcpy(s->b + s->n, p, n);
        s->n += n;
    }
}
static void p32(seed *s, uint32_t v, int big) {
    uint8_t b[4];
    for (int i = 0; i < 4; i++)
        b[big ? 3 - i : i] = (uint8_t)(v >> (8 * i));
    put(s, b, 4);
}
static void p16(seed *s, uint16_t v) {
    uint8_t b[2] = {(uint8_t)v, (uint8_t)(v >> 8)};
    put(s, b, 2);
}

static void from_writer(int fmt, int comp, const char *name) {
    char path[] = "/tmp/ft_events_fuzzXXXXXX", err[300];
    int fd = mkstemp(path);
    close(fd);
    ft_event ev[600];
    for (int i = 0; i < 600; i++) {
        ev[i].t = 100 + i * 37 + (i > 300 ? 20000000 : 0);
        ev[i].x = (uint16_t)(i % 346);
        ev[i].y = (uint16_t)((i * 13) % 260);
        ev[i].p = (uint8_t)(i % 3 == 0);
    }
    ft_ev_writer *w = ft_ev_writer_open(path, fmt, 346, 260, comp, err, sizeof err);
    if (!w) {
        fprintf(stderr, "writer: %s\n", err);
        failures++;
        return;
    }
    ft_ev_write(w, ev, 250);
    ft_ev_write(w, ev + 250, 350);
    ft_ev_writer_close(w, err, sizeof err);
    seed *s = &seeds[n_seeds++];
    FILE *f = fopen(path, "rb");
    s->n = fread(s->b, 1, MAXF, f);
    fclose(f);
    unlink(path);
    s->fmt = fmt;
    s->name = name;
}

static void build_seeds(void) {
    from_writer(FT_EV_AEDAT4, FT_EV_COMP_NONE, "f.aedat4");
    from_writer(FT_EV_AEDAT4, FT_EV_COMP_LZ4, "f.aedat4");
    from_writer(FT_EV_AEDAT4, FT_EV_COMP_ZSTD, "f.aedat4");
    from_writer(FT_EV_EVT3, 0, "f.raw");
    seed *s = &seeds[n_seeds++];
    s->fmt = FT_EV_EVT2;
    s->name = "g.raw";
    const char *h2 = "% evt 2.0\n% end\n";
    put(s, h2, strlen(h2));
    for (uint32_t i = 0; i < 400; i++)
        p32(s, i % 50 == 0 ? 0x80000000u | i : ((i & 1) << 28) | ((i % 64) << 22) | (i << 11) | i,
            0);
    s = &seeds[n_seeds++];
    s->fmt = FT_EV_DAT;
    s->name = "h.dat";
    const char *hd = "% Width 640\n% Height 480\n";
    put(s, hd, strlen(hd));
    uint8_t th[2] = {12, 8};
    put(s, th, 2);
    for (uint32_t i = 0; i < 300; i++) {
        p32(s, i * 11, 0);
        p32(s, ((i & 1) << 28) | ((i % 480) << 14) | (i % 640), 0);
    }
    s = &seeds[n_seeds++];
    s->fmt = FT_EV_AEDAT2;
    s->name = "i.aedat";
    const char *ha = "#!AER-DAT2.0\r\n# AEChip: DVS128\r\n";
    put(s, ha, strlen(ha));
    for (uint32_t i = 0; i < 300; i++) {
        p32(s, i % 40 == 0 ? 0x8000u : (i & 0x7FFFu), 1);
        p32(s, i * 5, 1);
    }
    s = &seeds[n_seeds++]; /* DAVIS: DVS, external input, APS and IMU words, x past the sensor */
    s->fmt = FT_EV_AEDAT2;
    s->name = "m.aedat";
    const char *hv = "#!AER-DAT2.0\r\n# AEChip: eu.seebetter.ini.chips.davis.DAVIS240C\r\n";
    put(s, hv, strlen(hv));
    for (uint32_t i = 0; i < 300; i++) {
        uint32_t kind = i % 7;
        p32(s,
            kind == 0   ? 0x80000C00u | (i << 12)
            : kind == 1 ? 0x80000000u | (i % 180) << 22 | (i % 240) << 12 | (i & 0x3FFu)
            : kind == 2 ? 0x400u
                        : ((i % 200) << 22) | ((i * 3 % 260) << 12) | ((i & 1) << 11),
            1);
        p32(s, i * 7, 1);
    }
    s = &seeds[n_seeds++];
    s->fmt = FT_EV_AEDAT3;
    s->name = "j.aedat";
    const char *h3 = "#!AER-DAT3.1\r\n#Source 1: DVS128\r\n#!END-HEADER\r\n";
    put(s, h3, strlen(h3));
    for (int k = 0; k < 4; k++) {
        uint32_t num = 40;
        p16(s, k == 2 ? 0 : 1);
        p16(s, 1);
        p32(s, 8, 0);
        p32(s, 4, 0);
        p32(s, (uint32_t)k, 0);
        p32(s, num, 0);
        p32(s, num, 0);
        p32(s, num, 0);
        for (uint32_t i = 0; i < num; i++) {
            p32(s, (i << 17) | (i << 2) | ((i & 1) << 1) | 1u, 0);
            p32(s, i * 3, 0);
        }
    }
    s = &seeds[n_seeds++];
    s->fmt = FT_EV_EVT3;
    s->name = "k.raw";
    const char *h4 = "% evt 3.0\n% time_offset_us 1712345678901234\n";
    put(s, h4, strlen(h4));
    for (uint16_t i = 0; i < 500; i++)
        p16(s, (uint16_t)((i % 11) << 12 | (i * 37 & 0xFFF)));
}

static ft_event evbuf[1 << 17], ref[1 << 17];

/* Reads all events; returns the count, *failed and *off the error state. */
static size_t read_input(const uint8_t *b, size_t n, int fmt, const char *name, ft_event *out,
                         int *opened, int *failed, long long *off) {
    char err[256];
    size_t total = 0;
    *failed = 0;
    *off = -1;
    ft_ev_reader *r = ft_ev_open_mem(b, n, fmt, name, err, sizeof err);
    *opened = r != NULL;
    if (!r)
        return 0;
    int keep = (int)below(2); /* half the runs keep trigger times and drain them in small pieces */
    ft_ev_keep_triggers(r, keep);
    for (;;) {
        size_t cap = 16 + below(3000);
        if (total + cap > (1 << 17))
            cap = (1 << 17) - total;
        if (cap < 16)
            break;
        long long got = ft_ev_read(r, out + total, cap);
        if (got < 0) {
            *failed = 1;
            *off = ft_ev_error_offset(r);
            if (*off < 0 || (size_t)*off > n || ft_ev_error(r)[0] == 0) {
                fprintf(stderr, "%s: error offset %lld outside the %zu-byte input\n", name, *off,
                        n);
                failures++;
            }
            break;
        }
        if (got == 0)
            break;
        total += (size_t)got;
        ft_ev_trigger trig[3];
        if (keep)
            ft_ev_triggers(r, trig, 1 + below(3));
    }
    ft_ev_close(r);
    return total;
}

int main(int argc, char **argv) {
    long iters = argc > 1 ? atol(argv[1]) : 20000;
    build_seeds();
    static uint8_t in[MAXF + 64];
    size_t truncations = 0, mutations = 0;
    for (long it = 0; it < iters; it++) {
        seed *s = &seeds[below(n_seeds)];
        size_t n = s->n;
        memcpy(in, s->b, n);
        int op = (int)below(6), opened, failed;
        long long off;
        if (op == 0) { /* truncation: events before the cut are exactly the whole file's */
            int o2, f2;
            long long off2;
            size_t full = read_input(s->b, s->n, s->fmt, s->name, ref, &o2, &f2, &off2);
            size_t cut = below(n);
            size_t got = read_input(in, cut, s->fmt, s->name, evbuf, &opened, &failed, &off);
            truncations++;
            if (got > full || memcmp(evbuf, ref, got * sizeof(ft_event)) != 0) {
                fprintf(stderr, "%s cut at %zu: %zu events, not a prefix of the %zu of the file\n",
                        s->name, cut, got, full);
                failures++;
            }
            continue;
        }
        int k = 1 + (int)below(8);
        for (int j = 0; j < k && n; j++) {
            size_t at = below(n);
            if (op == 1)
                in[at] ^= (uint8_t)(1u << below(8));
            else if (op == 2)
                in[at] = (uint8_t)rnd();
            else if (op == 3 && at + 4 <= n) {
                static const uint32_t ext[] = {0, 1, 0x7FFFFFFFu, 0x80000000u, 0xFFFFFFFFu, 28, 8};
                uint32_t v = ext[below(7)];
                memcpy(in + at, &v, 4);
            } else if (op == 4) { /* splice in a piece of another seed */
                seed *o = &seeds[below(n_seeds)];
                size_t from = below(o->n), len = below(64);
                if (from + len > o->n)
                    len = o->n - from;
                if (at + len > n)
                    len = n - at;
                memcpy(in + at, o->b + from, len);
            } else {
                n = below(n + 1);
            }
        }
        mutations++;
        int fmt = below(3) == 0 ? (int)below(7) : s->fmt;
        read_input(in, n, fmt, s->name, evbuf, &opened, &failed, &off);
    }
    if (failures) {
        fprintf(stderr, "fuzz_events: %d failures\n", failures);
        return 1;
    }
    printf("fuzz_events: %zu truncated and %zu mutated inputs over %zu seeds, no finding\n",
           truncations, mutations, n_seeds);
    return 0;
}
