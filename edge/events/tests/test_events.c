/* Unit tests of libflytrack_events on byte streams built here from the format descriptions (the
 * cross-checks against dv-processing, aedat and expelliarmus are in host/tests/events). Each
 * format: decoded fields, counter wraps, reading with the smallest buffer, and damage (every event
 * before it returned, then an error naming the offset). Built with ASan + UBSan. */
#define _POSIX_C_SOURCE 200809L
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/wait.h>
#include <unistd.h>

#include "flytrack/events.h"

#include "check.h" /* CHECK(), ft_test_failures: protocol/tests/check.h */

typedef struct {
    uint8_t b[1 << 16];
    size_t n;
} bytes;

static void add(bytes *s, const void *p, size_t n) {
    memcpy(s->b + s->n, p, n);
    s->n += n;
}
static void add_str(bytes *s, const char *t) {
    add(s, t, strlen(t));
}
static void le16(bytes *s, uint16_t v) {
    uint8_t p[2] = {(uint8_t)v, (uint8_t)(v >> 8)};
    add(s, p, 2);
}
static void le32(bytes *s, uint32_t v) {
    uint8_t p[4] = {(uint8_t)v, (uint8_t)(v >> 8), (uint8_t)(v >> 16), (uint8_t)(v >> 24)};
    add(s, p, 4);
}
static void be32(bytes *s, uint32_t v) {
    uint8_t p[4] = {(uint8_t)(v >> 24), (uint8_t)(v >> 16), (uint8_t)(v >> 8), (uint8_t)v};
    add(s, p, 4);
}

/* Reads everything with read calls of `cap` events; returns the count, *rc the last result. */
static size_t read_all(ft_ev_reader *r, ft_event *ev, size_t max, size_t cap, long long *rc) {
    size_t n = 0;
    for (;;) {
        size_t c = max - n < cap ? max - n : cap;
        long long got = ft_ev_read(r, ev + n, c);
        *rc = got;
        if (got <= 0)
            return n;
        n += (size_t)got;
    }
}

static ft_ev_reader *open_mem(const bytes *s, int fmt, const char *name) {
    char err[256];
    ft_ev_reader *r = ft_ev_open_mem(s->b, s->n, fmt, name, err, sizeof err);
    if (!r)
        fprintf(stderr, "open failed: %s\n", err);
    return r;
}

static void test_evt2(void) {
    bytes s = {.n = 0};
    add_str(&s, "% evt 2.0\n% format EVT2;height=720;width=1280\n% end\n");
    size_t hdr = s.n;
    le32(&s, 0x80000000u | 5u);                                /* TIME_HIGH 5 -> 320 us */
    le32(&s, (1u << 28) | (7u << 22) | (100u << 11) | 200u);   /* ON  t=327 x100 y200 */
    le32(&s, (0u << 28) | (63u << 22) | (1279u << 11) | 719u); /* OFF t=383 */
    le32(&s, 0xA0000000u | (1u << 8) | 1u);                    /* trigger */
    le32(&s, 0x80000000u | 3u);                                /* TIME_HIGH back: wrap */
    le32(&s, (1u << 28) | (1u << 22) | (2u << 11) | 3u);
    ft_ev_reader *r = open_mem(&s, FT_EV_AUTO, "a.raw");
    CHECK(r);
    if (!r)
        return;
    ft_ev_keep_triggers(r, 1);
    ft_event ev[64];
    long long rc;
    size_t n = read_all(r, ev, 64, 16, &rc);
    ft_ev_info info;
    ft_ev_get_info(r, &info);
    CHECK(info.format == FT_EV_EVT2 && info.width == 1280 && info.height == 720);
    ft_ev_trigger trig[4];
    CHECK(ft_ev_triggers(r, trig, 4) == 1 && trig[0].t == 320 && trig[0].value == 1 &&
          trig[0].channel == 1);
    CHECK(ft_ev_triggers(r, trig, 4) == 0); /* moved out */
    CHECK(rc == 0 && n == 3 && info.n_triggers == 1);
    CHECK(ev[0].t == 327 && ev[0].x == 100 && ev[0].y == 200 && ev[0].p == 1);
    CHECK(ev[1].t == 383 && ev[1].x == 1279 && ev[1].y == 719 && ev[1].p == 0);
    CHECK(ev[2].t == (1ll << 34) + 3 * 64 + 1);
    ft_ev_close(r);
    /* cut inside the 4th word: 3 events? no: 2 events before the damage, error names its offset */
    s.n = hdr + 4 * 3 + 2;
    r = open_mem(&s, FT_EV_AUTO, "a.raw");
    n = read_all(r, ev, 64, 16, &rc);
    CHECK(n == 2 && rc == -1);
    CHECK(ft_ev_error_offset(r) == (long long)(hdr + 12));
    CHECK(strstr(ft_ev_error(r), "truncated") != NULL);
    ft_ev_close(r);
}

static void test_evt3(void) {
    bytes s = {.n = 0};
    add_str(&s, "% evt 3.0\n% geometry 640x480\n");
    le16(&s, 0x8000u | 0xFFFu);       /* TIME_HIGH 0xFFF */
    le16(&s, 0x6000u | 0x010u);       /* TIME_LOW */
    le16(&s, 0x0000u | 33u);          /* ADDR_Y 33 */
    le16(&s, 0x2000u | 0x800u | 17u); /* ADDR_X ON x17 */
    le16(&s, 0x3000u | 100u);         /* VECT_BASE_X OFF 100 */
    le16(&s, 0x4000u | 0x801u);       /* VECT_12: x100, x111 */
    le16(&s, 0x5000u | 0x81u);        /* VECT_8: x112, x119 */
    le16(&s, 0xA000u | 1u);           /* trigger */
    le16(&s, 0xE000u);                /* OTHERS */
    le16(&s, 0x8000u | 1u);           /* TIME_HIGH 1 < 0xFFF: 24-bit wrap */
    le16(&s, 0x6000u | 2u);
    le16(&s, 0x2000u | 5u);
    ft_ev_reader *r = open_mem(&s, FT_EV_AUTO, "b.raw");
    CHECK(r);
    if (!r)
        return;
    ft_ev_keep_triggers(r, 1);
    ft_event ev[64];
    long long rc;
    size_t n = read_all(r, ev, 64, 16, &rc);
    ft_ev_info info;
    ft_ev_get_info(r, &info);
    CHECK(info.format == FT_EV_EVT3 && info.width == 640 && info.height == 480);
    CHECK(rc == 0 && n == 6 && info.n_triggers == 1);
    int64_t t0 = (0xFFFll << 12) | 0x10;
    CHECK(ev[0].t == t0 && ev[0].x == 17 && ev[0].y == 33 && ev[0].p == 1);
    CHECK(ev[1].x == 100 && ev[2].x == 111 && ev[3].x == 112 && ev[4].x == 119);
    CHECK(ev[1].p == 0 && ev[4].t == t0 && ev[4].y == 33);
    CHECK(ev[5].t == (1ll << 24) + (1 << 12) + 2 && ev[5].x == 5);
    ft_ev_trigger trig[4];
    CHECK(ft_ev_triggers(r, trig, 4) == 1 && trig[0].t == t0 && trig[0].value == 1);
    ft_ev_close(r);
}

static void test_dat(void) {
    bytes s = {.n = 0};
    add_str(&s, "% Data file containing CD events.\n% Version 2\n% Width 304\n% Height 240\n");
    uint8_t th[2] = {0x0C, 8};
    add(&s, th, 2);
    size_t hdr = s.n;
    le32(&s, 10);
    le32(&s, (1u << 28) | (5u << 14) | 300u);
    le32(&s, 0xFFFFFFF0u);
    le32(&s, (0u << 28) | (239u << 14) | 0u);
    le32(&s, 5); /* the 32-bit time wrapped */
    le32(&s, 0);
    ft_ev_reader *r = open_mem(&s, FT_EV_AUTO, "c.dat");
    CHECK(r);
    if (!r)
        return;
    ft_event ev[64];
    long long rc;
    size_t n = read_all(r, ev, 64, 16, &rc);
    ft_ev_info info;
    ft_ev_get_info(r, &info);
    CHECK(info.format == FT_EV_DAT && info.width == 304 && info.height == 240);
    CHECK(rc == 0 && n == 3);
    CHECK(ev[0].t == 10 && ev[0].x == 300 && ev[0].y == 5 && ev[0].p == 1);
    CHECK(ev[1].t == 0xFFFFFFF0ll && ev[1].y == 239 && ev[1].p == 0);
    CHECK(ev[2].t == (1ll << 32) + 5);
    ft_ev_close(r);
    s.n = hdr + 8 + 5;
    r = open_mem(&s, FT_EV_AUTO, "c.dat");
    n = read_all(r, ev, 64, 16, &rc);
    CHECK(n == 1 && rc == -1 && ft_ev_error_offset(r) == (long long)(hdr + 8));
    ft_ev_close(r);
}

static void test_aedat2(void) {
    bytes s = {.n = 0};
    add_str(&s, "#!AER-DAT2.0\r\n# This is a raw AE data file\r\n# AEChip: DVS128\r\n");
    be32(&s, (5u << 8) | (10u << 1) | 1u); /* raw bit 0 = 1: OFF; x mirrored */
    be32(&s, 1000);
    be32(&s, 0x8000u); /* sync */
    be32(&s, 1500);
    be32(&s, (127u << 8) | (0u << 1) | 0u);
    be32(&s, 2000);
    ft_ev_reader *r = open_mem(&s, FT_EV_AUTO, "d.aedat");
    CHECK(r);
    if (!r)
        return;
    ft_ev_keep_triggers(r, 1);
    ft_event ev[64];
    long long rc;
    size_t n = read_all(r, ev, 64, 16, &rc);
    ft_ev_info info;
    ft_ev_get_info(r, &info);
    CHECK(info.format == FT_EV_AEDAT2 && info.width == 128 && info.n_triggers == 1);
    CHECK(rc == 0 && n == 2);
    CHECK(ev[0].t == 1000 && ev[0].x == 117 && ev[0].y == 5 && ev[0].p == 0);
    CHECK(ev[1].t == 2000 && ev[1].x == 127 && ev[1].y == 127 && ev[1].p == 1);
    ft_ev_trigger trig[4];
    CHECK(ft_ev_triggers(r, trig, 4) == 1 && trig[0].t == 1500 && trig[0].value == 1);
    ft_ev_close(r);
}

/* DAVIS240C (jAER's DAVIS layout): DVS x mirrored over 240, polarity bit 11, APS and IMU words
 * skipped, an external input event a trigger; a chip whose layout is not known refused. */
static void test_aedat2_davis(void) {
    bytes s = {.n = 0};
    add_str(&s, "#!AER-DAT2.0\r\n# AEChip: eu.seebetter.ini.chips.davis.DAVIS240C\r\n");
    be32(&s, (170u << 22) | (10u << 12) | (1u << 11)); /* ON at field x 10, y 170 */
    be32(&s, 100);
    be32(&s, 0x80000000u | (5u << 22) | (6u << 12) | 512u); /* APS sample */
    be32(&s, 110);
    be32(&s, 0x80000C00u | (3u << 28)); /* IMU word */
    be32(&s, 120);
    be32(&s, 0x400u); /* external input */
    be32(&s, 130);
    be32(&s, (2u << 22) | (239u << 12)); /* OFF at field x 239 */
    be32(&s, 140);
    be32(&s, (2u << 22) | (240u << 12)); /* x field past the 240 columns: skipped */
    be32(&s, 150);
    ft_ev_reader *r = open_mem(&s, FT_EV_AUTO, "davis.aedat");
    CHECK(r);
    if (!r)
        return;
    ft_ev_keep_triggers(r, 1);
    ft_event ev[64];
    long long rc;
    size_t n = read_all(r, ev, 64, 16, &rc);
    ft_ev_info info;
    ft_ev_get_info(r, &info);
    CHECK(info.width == 240 && info.height == 180 && rc == 0 && n == 2);
    CHECK(info.n_triggers == 1 && info.n_skipped == 3);
    CHECK(ev[0].t == 100 && ev[0].x == 229 && ev[0].y == 170 && ev[0].p == 1);
    CHECK(ev[1].t == 140 && ev[1].x == 0 && ev[1].y == 2 && ev[1].p == 0);
    ft_ev_trigger trig[4];
    CHECK(ft_ev_triggers(r, trig, 4) == 1 && trig[0].t == 130);
    ft_ev_close(r);
    s.n = 0;
    add_str(&s, "#!AER-DAT2.0\r\n# AEChip: eu.seebetter.ini.chips.davis.DavisRGBW640\r\n");
    be32(&s, 1);
    be32(&s, 1);
    char err[300];
    CHECK(ft_ev_open_mem(s.b, s.n, FT_EV_AUTO, "rgbw.aedat", err, sizeof err) == NULL);
    CHECK(strstr(err, "DavisRGBW640") != NULL && strstr(err, "not known") != NULL);
}

static void a3_packet(bytes *s, int16_t type, int32_t size, int32_t overflow, int32_t number) {
    le16(s, (uint16_t)type);
    le16(s, 1);
    le32(s, (uint32_t)size);
    le32(s, 4);
    le32(s, (uint32_t)overflow);
    le32(s, (uint32_t)number);
    le32(s, (uint32_t)number);
    le32(s, (uint32_t)number);
}

static void test_aedat3(void) {
    bytes s = {.n = 0};
    add_str(&s, "#!AER-DAT3.1\r\n#Format: RAW\r\n#Source 1: DVS128\r\n#!END-HEADER\r\n");
    a3_packet(&s, 1, 8, 1, 3);
    le32(&s, (20u << 17) | (30u << 2) | (1u << 1) | 1u);
    le32(&s, 7);
    le32(&s, (21u << 17) | (31u << 2) | 0u); /* invalidated: skipped */
    le32(&s, 8);
    le32(&s, (22u << 17) | (32u << 2) | 1u);
    le32(&s, 9);
    a3_packet(&s, 0, 8, 0, 1); /* special: external input rising edge */
    le32(&s, (2u << 1) | 1u);
    le32(&s, 10);
    size_t last = s.n;
    a3_packet(&s, 1, 8, 0, 2);
    le32(&s, (1u << 17) | 1u);
    le32(&s, 11);
    le32(&s, (2u << 17) | 1u); /* cut below */
    le32(&s, 12);
    ft_ev_reader *r = open_mem(&s, FT_EV_AUTO, "e.aedat");
    CHECK(r);
    if (!r)
        return;
    ft_ev_keep_triggers(r, 1);
    ft_event ev[64];
    long long rc;
    size_t n = read_all(r, ev, 64, 16, &rc);
    ft_ev_info info;
    ft_ev_get_info(r, &info);
    CHECK(info.format == FT_EV_AEDAT3 && info.width == 128 && info.n_triggers == 1);
    CHECK(rc == 0 && n == 4);
    CHECK(ev[0].t == (1ll << 31) + 7 && ev[0].x == 20 && ev[0].y == 30 && ev[0].p == 1);
    CHECK(ev[1].t == (1ll << 31) + 9 && ev[1].x == 22 && ev[1].p == 0);
    CHECK(ev[3].t == 12 && ev[3].x == 2);
    ft_ev_trigger trig[4];
    CHECK(ft_ev_triggers(r, trig, 4) == 1 && trig[0].t == 10 && trig[0].value == 1);
    ft_ev_close(r);
    s.n -= 3;
    r = open_mem(&s, FT_EV_AUTO, "e.aedat");
    n = read_all(r, ev, 64, 16, &rc);
    CHECK(n == 2 && rc == -1 && ft_ev_error_offset(r) == (long long)last);
    ft_ev_close(r);
}

/* Writers round trip through the readers, AEDAT 4.0 in every compression, across packets. */
static void test_writers(void) {
    enum { N = 70000 };
    ft_event *ev = calloc(N, sizeof *ev), *back = calloc(N + 16, sizeof *back);
    int64_t t = 3;
    for (int i = 0; i < N; i++) {
        t += (i % 97 == 0) ? 5000000 : (i % 3); /* gaps well past EVT 3.0's 24-bit wrap */
        ev[i].t = t;
        ev[i].x = (uint16_t)((i * 7) % 1280);
        ev[i].y = (uint16_t)((i / 5) % 720);
        ev[i].p = (uint8_t)(i & 1);
    }
    char path[] = "/tmp/ft_events_testXXXXXX";
    int fd = mkstemp(path);
    close(fd);
    int cases[][2] = {{FT_EV_AEDAT4, FT_EV_COMP_NONE},
                      {FT_EV_AEDAT4, FT_EV_COMP_LZ4},
                      {FT_EV_AEDAT4, FT_EV_COMP_ZSTD},
                      {FT_EV_EVT3, 0}};
    for (size_t c = 0; c < 4; c++) {
        char err[300];
        ft_ev_writer *w =
            ft_ev_writer_open(path, cases[c][0], 1280, 720, cases[c][1], err, sizeof err);
        CHECK(w);
        if (!w)
            continue;
        CHECK(ft_ev_write(w, ev, 1000) == 0);
        CHECK(ft_ev_write(w, ev, 10) == -1); /* back in time: refused, writer goes on */
        CHECK(ft_ev_write(w, ev + 1000, N - 1000) == 0);
        CHECK(ft_ev_writer_close(w, err, sizeof err) == 0);
        ft_ev_reader *r = ft_ev_open(path, FT_EV_AUTO, err, sizeof err);
        CHECK(r);
        if (!r)
            continue;
        long long rc;
        size_t n = read_all(r, back, N + 16, 4096, &rc);
        ft_ev_info info;
        ft_ev_get_info(r, &info);
        CHECK(rc == 0 && n == N && info.format == cases[c][0]);
        CHECK(info.width == 1280 && info.height == 720);
        size_t bad = 0;
        for (size_t i = 0; i < n && i < N; i++)
            bad += back[i].t != ev[i].t || back[i].x != ev[i].x || back[i].y != ev[i].y ||
                   back[i].p != ev[i].p;
        CHECK(bad == 0);
        if (bad)
            fprintf(stderr, "format %d compression %d: %zu events differ\n", cases[c][0],
                    cases[c][1], bad);
        ft_ev_close(r);
        /* the same file through a pipe: the chunked read() path (regular files are mapped) */
        int fds[2];
        CHECK(pipe(fds) == 0);
        pid_t child = fork();
        if (child == 0) {
            close(fds[0]);
            FILE *f = fopen(path, "rb");
            char chunk[7919]; /* odd size: units split across reads */
            size_t got;
            while (f && (got = fread(chunk, 1, sizeof chunk, f)) > 0)
                if (write(fds[1], chunk, got) != (ssize_t)got)
                    break;
            _exit(0);
        }
        close(fds[1]);
        char dev[64];
        snprintf(dev, sizeof dev, "/dev/fd/%d", fds[0]);
        r = ft_ev_open(dev, FT_EV_AUTO, err, sizeof err);
        CHECK(r);
        if (r) {
            size_t m = read_all(r, back, N + 16, 1000, &rc);
            CHECK(rc == 0 && m == N);
            CHECK(memcmp(back, ev, sizeof(ft_event) * N) == 0);
            ft_ev_close(r);
        }
        close(fds[0]);
        waitpid(child, NULL, 0);
    }
    unlink(path);
    free(ev);
    free(back);
}

/* EVT 3.0 of Unix-epoch times: rebased by whole 2^24 us ranges (the header keeps the offset), so
 * the file is a few words, not two TIME_HIGH words per range since 1970; read back unchanged. */
static void test_evt3_epoch_times(void) {
    ft_event ev[3], back[32];
    memset(ev, 0, sizeof ev);
    for (int i = 0; i < 3; i++) {
        ev[i].t = 1712345678901234ll + 30000000ll * i; /* 30 s apart: wraps between them too */
        ev[i].x = (uint16_t)(10 + i);
        ev[i].y = (uint16_t)(20 + i);
        ev[i].p = (uint8_t)(i & 1);
    }
    char path[] = "/tmp/ft_events_epochXXXXXX", err[300];
    int fd = mkstemp(path);
    close(fd);
    ft_ev_writer *w = ft_ev_writer_open(path, FT_EV_EVT3, 640, 480, 0, err, sizeof err);
    CHECK(w && ft_ev_write(w, ev, 3) == 0);
    int64_t off = w ? ft_ev_writer_time_offset(w) : -1;
    CHECK(off > 0 && off % (1ll << 24) == 0 && ev[0].t - off < (1ll << 24));
    CHECK(ft_ev_writer_close(w, err, sizeof err) == 0);
    FILE *f = fopen(path, "rb");
    long size = -1;
    if (f && fseek(f, 0, SEEK_END) == 0)
        size = ftell(f);
    if (f)
        fclose(f);
    CHECK(size > 0 && size < 400);
    ft_ev_reader *r = ft_ev_open(path, FT_EV_AUTO, err, sizeof err);
    CHECK(r);
    if (r) {
        long long rc;
        size_t n = read_all(r, back, 32, 16, &rc);
        ft_ev_info info;
        ft_ev_get_info(r, &info);
        CHECK(rc == 0 && n == 3 && info.time_offset == off);
        CHECK(memcmp(back, ev, sizeof ev) == 0);
        ft_ev_close(r);
    }
    unlink(path);
}

/* Triggers through both writers and back: EVT 3.0 places them among the events by time (one
 * before the first event, one between, one after the last, held until close); what a format cannot
 * hold (channel 16 in EVT 3.0, a time already passed) is left out and counted; AEDAT 4.0 writes a
 * trigger stream only when opened with FT_EV_W_TRIGGERS. */
static void test_writer_triggers(void) {
    ft_event ev[4];
    memset(ev, 0, sizeof ev);
    int64_t et[4] = {1000, 2000, 2000, 40000000}; /* the last past a 2^24 us wrap */
    for (int i = 0; i < 4; i++) {
        ev[i].t = et[i];
        ev[i].x = (uint16_t)(5 + i);
        ev[i].y = 7;
        ev[i].p = 1;
    }
    ft_ev_trigger tr[5];
    memset(tr, 0, sizeof tr);
    int64_t tt[5] = {500, 1500, 1500, 50000000, 60000000};
    uint8_t tv[5] = {1, 0, 1, 1, 0}, tc[5] = {2, 2, 16, 0, 15};
    for (int i = 0; i < 5; i++) {
        tr[i].t = tt[i];
        tr[i].value = tv[i];
        tr[i].channel = tc[i];
    }
    char path[] = "/tmp/ft_events_trigXXXXXX", err[300];
    int fd = mkstemp(path);
    close(fd);
    for (int fmt = FT_EV_AEDAT4; fmt <= FT_EV_EVT3; fmt += FT_EV_EVT3 - FT_EV_AEDAT4) {
        ft_ev_writer *w = ft_ev_writer_open(path, fmt, 64, 64, 0, err, sizeof err);
        if (fmt == FT_EV_AEDAT4) { /* no trigger stream declared: refused, nothing written */
            CHECK(w && ft_ev_write_triggers(w, tr, 1) == -1);
            CHECK(w && strstr(ft_ev_writer_error(w), "FT_EV_W_TRIGGERS") != NULL);
            CHECK(ft_ev_writer_close(w, err, sizeof err) == 0);
            w = ft_ev_writer_open_ex(path, fmt, 64, 64, 0, FT_EV_W_TRIGGERS, err, sizeof err);
        }
        CHECK(w);
        if (!w)
            continue;
        long long dropped = ft_ev_write_triggers(w, tr, 3); /* 500, 1500, 1500 (channel 16) */
        CHECK(dropped == (fmt == FT_EV_EVT3 ? 1 : 0));
        CHECK(ft_ev_write(w, ev, 4) == 0);
        CHECK(ft_ev_write_triggers(w, tr, 1) == 1);     /* 500 again: before what is written */
        CHECK(ft_ev_write_triggers(w, tr + 3, 2) == 0); /* after the last event: held to close */
        CHECK(ft_ev_writer_close(w, err, sizeof err) == 0);
        ft_ev_reader *r = ft_ev_open(path, FT_EV_AUTO, err, sizeof err);
        CHECK(r);
        if (!r)
            continue;
        ft_ev_keep_triggers(r, 1);
        ft_event back[32];
        long long rc;
        size_t n = read_all(r, back, 32, 16, &rc);
        CHECK(rc == 0 && n == 4 && memcmp(back, ev, sizeof ev) == 0);
        ft_ev_trigger got[16];
        size_t m = ft_ev_triggers(r, got, 16);
        int64_t want_t[5] = {500, 1500, 1500, 50000000, 60000000};
        int want[5] = {1, 1, fmt == FT_EV_AEDAT4, 1, 1}; /* EVT 3.0 left channel 16 out */
        size_t k = 0, ok = 1;
        for (int i = 0; i < 5; i++) {
            if (!want[i])
                continue;
            ok &= k < m && got[k].t == want_t[i] && got[k].value == tv[i] &&
                  got[k].channel == (fmt == FT_EV_EVT3 ? tc[i] : 0);
            k++;
        }
        CHECK(ok && m == k);
        if (!ok || m != k)
            fprintf(stderr, "format %d: %zu triggers read back\n", fmt, m);
        ft_ev_close(r);
    }
    unlink(path);
}

static void test_bad_open(void) {
    char err[256];
    CHECK(ft_ev_open("/nonexistent/x.aedat4", FT_EV_AUTO, err, sizeof err) == NULL);
    CHECK(strstr(err, "cannot open") != NULL);
    bytes s = {.n = 0};
    add_str(&s, "hello world, no header here");
    CHECK(ft_ev_open_mem(s.b, s.n, FT_EV_AUTO, "x.bin", err, sizeof err) == NULL);
    CHECK(strstr(err, "unknown event file format") != NULL);
    s.n = 0;
    add_str(&s, "#!AER-DAT4.0\r\n");
    le32(&s, 100);
    CHECK(ft_ev_open_mem(s.b, s.n, FT_EV_AUTO, "x.aedat4", err, sizeof err) == NULL);
    CHECK(strstr(err, "at byte 14") != NULL);
}

int main(void) {
    test_evt2();
    test_evt3();
    test_dat();
    test_aedat2();
    test_aedat2_davis();
    test_aedat3();
    test_writers();
    test_evt3_epoch_times();
    test_writer_triggers();
    test_bad_open();
    if (ft_test_failures) {
        fprintf(stderr, "test_events: %d checks failed\n", ft_test_failures);
        return 1;
    }
    printf("test_events: all checks passed\n");
    return 0;
}
