/* Event-file writers: AEDAT 4.0 (an event stream, id 0, packets of at most 32768 events, and when
 * asked a trigger stream, id 1; uncompressed, LZ4 frame or Zstd) and Prophesee EVT 3.0 (TIME_HIGH
 * / TIME_LOW / ADDR_Y, ADDR_X for single events, VECT_BASE_X + VECT_12 for runs along a row at one
 * time and polarity, EXT_TRIGGER for triggers).
 *
 * AEDAT 4.0 is written without a data table (dataTablePosition = -1): a reader then scans the
 * packets, and a recording cut off at any packet boundary (a killed process) stays readable. */
#include <errno.h>
#include <lz4frame.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <zstd.h>

#include "flytrack/events.h"

#define A4_MAX_PACKET 32768
#define A4_EVENT_STREAM 0u
#define A4_TRIGGER_STREAM 1u
#define EVT3_WORDS 32768 /* words built before they go to the file */

struct ft_ev_writer {
    FILE *f;
    char path[160];
    int format, compression, failed;
    int triggers; /* triggers may be written: EVT 3.0 always, AEDAT 4.0 with FT_EV_W_TRIGGERS */
    char err[420];
    int64_t last_t;    /* of the last event (EVT 3.0: or trigger) written */
    int64_t last_trig; /* of the last trigger taken */
    /* EVT 3.0 state: the last TIME_HIGH (full count of 4096-us steps), whether one is out yet,
     * the row of the last ADDR_Y (-1: none yet) */
    int64_t th_full;
    int th_out;
    int y;
    int64_t t_rel; /* the time (less time_offset) the stream is at, once th_out */
    uint8_t *words;
    size_t nw;
    /* triggers: EVT 3.0 holds them until an event passes their time (the stream is in time
     * order), AEDAT 4.0 builds a packet in it */
    ft_ev_trigger *tq;
    size_t tq_n, tq_head, tq_bytes;
    /* EVT 3.0 header: written with the first event (or at close), which decides time_offset */
    int width, height, header_out;
    int64_t time_offset;
    /* scratch */
    uint8_t *pkt, *comp;
    size_t pkt_cap, comp_cap;
};

static void wfail(ft_ev_writer *w, const char *fmt, ...) __attribute__((format(printf, 2, 3)));
static void wfail(ft_ev_writer *w, const char *fmt, ...) {
    char msg[240];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(msg, sizeof msg, fmt, ap);
    va_end(ap);
    snprintf(w->err, sizeof w->err, "%s: %s", w->path, msg);
    w->failed = 1;
}

static void st32(uint8_t *p, uint32_t v) {
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
    p[2] = (uint8_t)(v >> 16);
    p[3] = (uint8_t)(v >> 24);
}
static void st16(uint8_t *p, uint16_t v) {
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
}
static void st64(uint8_t *p, uint64_t v) {
    st32(p, (uint32_t)v);
    st32(p + 4, (uint32_t)(v >> 32));
}

static int put(ft_ev_writer *w, const void *b, size_t n) {
    if (n && fwrite(b, 1, n, w->f) != n) {
        wfail(w, "write error: %s", strerror(errno));
        return -1;
    }
    return 0;
}

static int grow(ft_ev_writer *w, uint8_t **b, size_t *cap, size_t want) {
    if (want <= *cap)
        return 0;
    uint8_t *nb = realloc(*b, want);
    if (!nb) {
        wfail(w, "out of memory");
        return -1;
    }
    *b = nb;
    *cap = want;
    return 0;
}

static const char *comp_name(int c) {
    static const char *const names[] = {"NONE", "LZ4", "LZ4_HIGH", "ZSTD", "ZSTD_HIGH"};
    return names[c];
}

/* IOHeader FlatBuffer laid out as dv writes it: root offset, "IOHE", vtable (3 fields), table
 * {soffset, i32 compression, u32 -> infoNode, i64 dataTablePosition}, the XML string. */
static int a4_header(ft_ev_writer *w, int width, int height) {
    char trig[900] = "", xml[3072];
    if (w->triggers) /* stream 1, declared as dv declares its trigger output */
        snprintf(trig, sizeof trig,
                 "        <node name=\"1\" path=\"/outInfo/1/\">\n"
                 "            <attr key=\"compression\" type=\"string\">%s</attr>\n"
                 "            <attr key=\"originalModuleName\" type=\"string\">flytrack</attr>\n"
                 "            <attr key=\"originalOutputName\" type=\"string\">triggers</attr>\n"
                 "            <attr key=\"typeDescription\" type=\"string\">Array of "
                 "triggers.</attr>\n"
                 "            <attr key=\"typeIdentifier\" type=\"string\">TRIG</attr>\n"
                 "            <node name=\"info\" path=\"/outInfo/1/info/\">\n"
                 "                <attr key=\"source\" type=\"string\">FlyTrack</attr>\n"
                 "            </node>\n"
                 "        </node>\n",
                 comp_name(w->compression));
    int xl = snprintf(
        xml, sizeof xml,
        "<dv version=\"2.0\">\n"
        "    <node name=\"outInfo\" path=\"/outInfo/\">\n"
        "        <node name=\"0\" path=\"/outInfo/0/\">\n"
        "            <attr key=\"compression\" type=\"string\">%s</attr>\n"
        "            <attr key=\"originalModuleName\" type=\"string\">flytrack</attr>\n"
        "            <attr key=\"originalOutputName\" type=\"string\">events</attr>\n"
        "            <attr key=\"typeDescription\" type=\"string\">Array of events (polarity "
        "ON/OFF).</attr>\n"
        "            <attr key=\"typeIdentifier\" type=\"string\">EVTS</attr>\n"
        "            <node name=\"info\" path=\"/outInfo/0/info/\">\n"
        "                <attr key=\"sizeX\" type=\"int\">%d</attr>\n"
        "                <attr key=\"sizeY\" type=\"int\">%d</attr>\n"
        "                <attr key=\"source\" type=\"string\">FlyTrack</attr>\n"
        "            </node>\n"
        "        </node>\n"
        "%s"
        "    </node>\n"
        "</dv>\n",
        comp_name(w->compression), width, height, trig);
    uint8_t b[3200];
    memset(b, 0, sizeof b);
    size_t total = 44 + 4 + (size_t)xl + 1;
    while (total % 8 != 4) /* keeps dataTablePosition 8-aligned from the buffer's end, as dv */
        total++;
    st32(b, 24);              /* root table at 24 */
    memcpy(b + 4, "IOHE", 4); /* file identifier */
    st16(b + 14, 10);         /* vtable at 14: 10 bytes */
    st16(b + 16, 20);         /* table size */
    st16(b + 18, 4);          /* field 0 compression at +4 */
    st16(b + 20, 12);         /* field 1 dataTablePosition at +12 */
    st16(b + 22, 8);          /* field 2 infoNode at +8 */
    st32(b + 24, 24 - 14);    /* table -> vtable */
    st32(b + 28, (uint32_t)w->compression);
    st32(b + 32, 44 - 32); /* -> string at 44 */
    st64(b + 36, (uint64_t)(int64_t)-1);
    st32(b + 44, (uint32_t)xl);
    memcpy(b + 48, xml, (size_t)xl);
    uint8_t sz[4];
    st32(sz, (uint32_t)total);
    if (put(w, "#!AER-DAT4.0\r\n", 14) < 0 || put(w, sz, 4) < 0 || put(w, b, total) < 0)
        return -1;
    return 0;
}

/* One AEDAT 4.0 packet of the raw FlatBuffer b[0..raw) (size-prefixed, as dv writes them), in the
 * file's compression, under stream id `stream`. */
static int a4_put_packet(ft_ev_writer *w, uint32_t stream, const uint8_t *b, size_t raw) {
    const uint8_t *out = b;
    size_t out_len = raw;
    if (w->compression == FT_EV_COMP_LZ4 || w->compression == FT_EV_COMP_LZ4_HIGH) {
        LZ4F_preferences_t prefs;
        memset(&prefs, 0, sizeof prefs);
        prefs.compressionLevel = w->compression == FT_EV_COMP_LZ4_HIGH ? 9 : 0;
        size_t bound = LZ4F_compressFrameBound(raw, &prefs);
        if (grow(w, &w->comp, &w->comp_cap, bound) < 0)
            return -1;
        size_t got = LZ4F_compressFrame(w->comp, bound, b, raw, &prefs);
        if (LZ4F_isError(got)) {
            wfail(w, "LZ4 compression failed: %s", LZ4F_getErrorName(got));
            return -1;
        }
        out = w->comp;
        out_len = got;
    } else if (w->compression == FT_EV_COMP_ZSTD || w->compression == FT_EV_COMP_ZSTD_HIGH) {
        size_t bound = ZSTD_compressBound(raw);
        if (grow(w, &w->comp, &w->comp_cap, bound) < 0)
            return -1;
        size_t got =
            ZSTD_compress(w->comp, bound, b, raw, w->compression == FT_EV_COMP_ZSTD_HIGH ? 9 : 3);
        if (ZSTD_isError(got)) {
            wfail(w, "Zstd compression failed: %s", ZSTD_getErrorName(got));
            return -1;
        }
        out = w->comp;
        out_len = got;
    }
    uint8_t h[8];
    st32(h, stream);
    st32(h + 4, (uint32_t)out_len);
    return put(w, h, 8) < 0 || put(w, out, out_len) < 0 ? -1 : 0;
}

static int a4_packet(ft_ev_writer *w, const ft_event *ev, size_t n) {
    size_t raw = 32 + 16 * n;
    if (grow(w, &w->pkt, &w->pkt_cap, raw) < 0)
        return -1;
    uint8_t *b = w->pkt;
    memset(b, 0, 32);
    st32(b, (uint32_t)(raw - 4)); /* size prefix */
    st32(b + 4, 16);              /* root table at 4 + 16 */
    memcpy(b + 8, "EVTS", 4);
    st16(b + 14, 6); /* vtable: 6 bytes */
    st16(b + 16, 8); /* table size */
    st16(b + 18, 4); /* field 0 (elements) at +4 */
    st32(b + 20, 6); /* table at 20 -> vtable at 14 */
    st32(b + 24, 4); /* -> vector at 28 */
    st32(b + 28, (uint32_t)n);
    for (size_t i = 0; i < n; i++) {
        uint8_t *e = b + 32 + 16 * i;
        st64(e, (uint64_t)ev[i].t);
        st16(e + 8, ev[i].x);
        st16(e + 10, ev[i].y);
        e[12] = ev[i].p ? 1 : 0;
        e[13] = e[14] = e[15] = 0;
    }
    return a4_put_packet(w, A4_EVENT_STREAM, b, raw);
}

/* A TriggerPacket (dv's "TRIG": a table whose field 0 is a vector of Trigger tables, each
 * {timestamp: int64 (field 0), type: int8 (field 1)}), laid out with offsets from the size prefix
 * so every int64 is 8-aligned as dv's verifier wants: prefix, root offset, "TRIG", the packet's
 * vtable and table, the vector of offsets, one vtable that all Trigger tables share, the tables of
 * 16 bytes (soffset, type and 3 pad, timestamp). Type 1 is an external signal's rising edge, 2 its
 * falling edge. */
static int a4_trigger_packet(ft_ev_writer *w, const ft_ev_trigger *tr, size_t n) {
    size_t vt = 32 + 4 * n, first = (vt + 8 + 7) & ~(size_t)7, raw = first + 16 * n;
    if (grow(w, &w->pkt, &w->pkt_cap, raw) < 0)
        return -1;
    uint8_t *b = w->pkt;
    memset(b, 0, raw);
    st32(b, (uint32_t)(raw - 4)); /* size prefix */
    st32(b + 4, 16);              /* root table at 4 + 16 */
    memcpy(b + 8, "TRIG", 4);
    st16(b + 12, 6); /* the packet's vtable at 12: 6 bytes */
    st16(b + 14, 8); /* table size */
    st16(b + 16, 4); /* field 0 (elements) at +4 */
    st32(b + 20, 8); /* table at 20 -> vtable at 12 */
    st32(b + 24, 4); /* -> vector at 28 */
    st32(b + 28, (uint32_t)n);
    st16(b + vt, 8);      /* Trigger vtable: 8 bytes */
    st16(b + vt + 2, 16); /* table size */
    st16(b + vt + 4, 8);  /* field 0 timestamp at +8 */
    st16(b + vt + 6, 4);  /* field 1 type at +4 */
    for (size_t i = 0; i < n; i++) {
        size_t e = first + 16 * i, slot = 32 + 4 * i;
        st32(b + slot, (uint32_t)(e - slot));
        st32(b + e, (uint32_t)(e - vt));
        b[e + 4] = tr[i].value ? 1 : 2;
        st64(b + e + 8, (uint64_t)tr[i].t);
    }
    return a4_put_packet(w, A4_TRIGGER_STREAM, b, raw);
}

/* Room for `count` triggers in tq. */
static int tq_reserve(ft_ev_writer *w, size_t count) {
    if (count * sizeof *w->tq <= w->tq_bytes)
        return 0;
    ft_ev_trigger *nq = realloc(w->tq, count * sizeof *w->tq);
    if (!nq) {
        wfail(w, "out of memory holding %zu triggers", count);
        return -1;
    }
    w->tq = nq;
    w->tq_bytes = count * sizeof *w->tq;
    return 0;
}

/* ---- EVT 3.0 ------------------------------------------------------------------------------- */

static int evt3_flush(ft_ev_writer *w) {
    int rc = put(w, w->words, 2 * w->nw);
    w->nw = 0;
    return rc;
}

static inline int evt3_word(ft_ev_writer *w, unsigned v) {
    if (w->nw == EVT3_WORDS && evt3_flush(w) < 0)
        return -1;
    st16(w->words + 2 * w->nw++, (uint16_t)v);
    return 0;
}

/* EVT 3.0 keeps 24 bits of time, so a reader counts the 2^24 us wraps itself, and Prophesee's
 * reference decoding counts one only when a TIME_HIGH falls from near the top of its range
 * (within 10 steps of 4095) to near the bottom, as a camera's stream does: one that falls less is
 * taken for a word out of order. So each wrap is written as a camera marks it, TIME_HIGH 4095 then
 * TIME_HIGH 0, however long the gap; any reader that counts a fall of half the range, or any
 * fall, counts these too. Puts the stream's time at t (relative to time_offset): TIME_HIGH when
 * its 4096 us step changed, then TIME_LOW; TIME_LOW alone when only that did. */
static int evt3_time(ft_ev_writer *w, int64_t t) {
    int64_t th = t >> 12;
    if (w->th_out && th == w->th_full) {
        if (t != w->t_rel && evt3_word(w, 0x6000u | (unsigned)(t & 0xFFF)) < 0)
            return -1;
        w->t_rel = t;
        return 0;
    }
    while ((th >> 12) > (w->th_full >> 12)) { /* a wrap between the last time and t */
        if (((w->th_full & 0xFFF) != 0xFFF || !w->th_out) && evt3_word(w, 0x8FFFu) < 0)
            return -1;
        if (evt3_word(w, 0x8000u) < 0)
            return -1;
        w->th_full = ((w->th_full >> 12) + 1) << 12;
        w->th_out = 1;
    }
    if ((th != w->th_full || !w->th_out) && evt3_word(w, 0x8000u | (unsigned)(th & 0xFFF)) < 0)
        return -1;
    w->th_full = th;
    w->th_out = 1;
    w->t_rel = t;
    return evt3_word(w, 0x6000u | (unsigned)(t & 0xFFF));
}

/* Writes the held triggers whose time is at most t_abs (all of them for INT64_MAX) as
 * EXT_TRIGGER words (bits 11..8 the channel, bit 0 the edge) at their own times. */
static int evt3_triggers_upto(ft_ev_writer *w, int64_t t_abs) {
    while (w->tq_head < w->tq_n && w->tq[w->tq_head].t <= t_abs) {
        const ft_ev_trigger *q = &w->tq[w->tq_head++];
        if (evt3_time(w, q->t - w->time_offset) < 0 ||
            evt3_word(w, 0xA000u | ((unsigned)q->channel << 8) | (q->value ? 1u : 0u)) < 0)
            return -1;
        w->last_t = q->t;
    }
    if (w->tq_head == w->tq_n)
        w->tq_head = w->tq_n = 0;
    return 0;
}

static int evt3_events(ft_ev_writer *w, const ft_event *ev, size_t n) {
    for (size_t i = 0; i < n; i++) {
        if (w->tq_n && evt3_triggers_upto(w, ev[i].t) < 0)
            return -1;
        if (evt3_time(w, ev[i].t - w->time_offset) < 0)
            return -1;
        if (ev[i].y != w->y) {
            w->y = ev[i].y;
            if (evt3_word(w, (unsigned)w->y & 0x7FFu) < 0)
                return -1;
        }
        /* A run of events with this time, row and polarity at rising x within 12 columns goes out
         * as VECT_BASE_X + VECT_12 (a reader emits a vector's events in rising x: same order). */
        size_t run = 1;
        while (i + run < n && run < 12 && ev[i + run].t == ev[i].t && ev[i + run].y == ev[i].y &&
               !ev[i + run].p == !ev[i].p && ev[i + run].x > ev[i + run - 1].x &&
               ev[i + run].x - ev[i].x < 12)
            run++;
        unsigned pol = ev[i].p ? 0x800u : 0u;
        if (run >= 2 && ev[i].x + 12u <= 2048u) {
            unsigned mask = 0;
            for (size_t j = 0; j < run; j++)
                mask |= 1u << (ev[i + j].x - ev[i].x);
            if (evt3_word(w, 0x3000u | pol | (ev[i].x & 0x7FFu)) < 0 ||
                evt3_word(w, 0x4000u | mask) < 0)
                return -1;
            i += run - 1;
        } else if (evt3_word(w, 0x2000u | pol | (ev[i].x & 0x7FFu)) < 0) {
            return -1;
        }
        w->last_t = ev[i].t;
    }
    return evt3_flush(w);
}

/* The EVT 3.0 header, written once the first time is known (the first event's, or a held
 * trigger's before it). EVT 3.0 counts time from 0 in 2^24 us ranges that a reader must see wrap
 * one by one, so a recording whose clock is far from 0 (DV stamps its events in Unix-epoch
 * microseconds) would need two TIME_HIGH words for each of the ~10^8 ranges before its first
 * event: hundreds of MB of nothing. Such times are written less the whole ranges before the first
 * one, and that offset is kept in the header line "% time_offset_us N", which ft_ev_open adds
 * back; a reader that does not know the line sees times counted from the start of the first
 * range, as Prophesee's own time shifting does. */
static int evt3_header(ft_ev_writer *w, int64_t first_t) {
    if (w->tq_n > w->tq_head && w->tq[w->tq_head].t < first_t)
        first_t = w->tq[w->tq_head].t;
    w->time_offset = first_t - (first_t & ((INT64_C(1) << 24) - 1));
    char h[320], off[48] = "";
    if (w->time_offset)
        snprintf(off, sizeof off, "%% time_offset_us %lld\n", (long long)w->time_offset);
    int hl = snprintf(h, sizeof h,
                      "%% evt 3.0\n%% format EVT3;height=%d;width=%d\n%% geometry %dx%d\n"
                      "%% integrator_name FlyTrack\n%s%% end\n",
                      w->height, w->width, w->width, w->height, off);
    w->header_out = 1;
    return put(w, h, (size_t)hl);
}

/* ---- the API ------------------------------------------------------------------------------- */

ft_ev_writer *ft_ev_writer_open_ex(const char *path, int format, int width, int height,
                                   int compression, unsigned flags, char *err, size_t err_len) {
    if (format != FT_EV_AEDAT4 && format != FT_EV_EVT3) {
        snprintf(err, err_len, "%s: writing %s is not supported (aedat4 and evt3 are)", path,
                 ft_ev_format_name(format));
        return NULL;
    }
    if (format == FT_EV_AEDAT4 && (compression < 0 || compression > FT_EV_COMP_ZSTD_HIGH)) {
        snprintf(err, err_len, "%s: unknown AEDAT 4.0 compression %d", path, compression);
        return NULL;
    }
    if (width <= 0 || height <= 0 || width > 2048 || height > 2048) {
        snprintf(err, err_len, "%s: sensor size %dx%d out of range (1..2048)", path, width, height);
        return NULL;
    }
    ft_ev_writer *w = calloc(1, sizeof *w);
    if (!w) {
        snprintf(err, err_len, "%s: out of memory", path);
        return NULL;
    }
    snprintf(w->path, sizeof w->path, "%s", path);
    w->format = format;
    w->compression = format == FT_EV_AEDAT4 ? compression : 0;
    w->triggers = format == FT_EV_EVT3 || (flags & FT_EV_W_TRIGGERS);
    w->last_t = w->last_trig = INT64_MIN;
    w->y = -1;
    w->width = width;
    w->height = height;
    if (format == FT_EV_EVT3 && !(w->words = malloc(2 * EVT3_WORDS))) {
        snprintf(err, err_len, "%s: out of memory", path);
        free(w);
        return NULL;
    }
    w->f = fopen(path, "wb");
    if (!w->f) {
        snprintf(err, err_len, "%s: cannot create: %s", path, strerror(errno));
        free(w->words);
        free(w);
        return NULL;
    }
    if (format == FT_EV_AEDAT4 && a4_header(w, width, height) < 0) { /* EVT 3.0: evt3_header */
        snprintf(err, err_len, "%s", w->err);
        fclose(w->f);
        free(w);
        return NULL;
    }
    return w;
}

ft_ev_writer *ft_ev_writer_open(const char *path, int format, int width, int height,
                                int compression, char *err, size_t err_len) {
    return ft_ev_writer_open_ex(path, format, width, height, compression, 0, err, err_len);
}

int ft_ev_write(ft_ev_writer *w, const ft_event *ev, size_t n) {
    if (w->failed)
        return -1;
    int64_t last = w->last_t;
    for (size_t i = 0; i < n; i++) {
        if (ev[i].t < last || ev[i].t < 0) {
            wfail(w,
                  "event %zu of this call goes back in time (t=%lld after %lld, or negative): "
                  "both formats need non-decreasing times",
                  i, (long long)ev[i].t, (long long)last);
            w->failed = 0; /* nothing of this call written; the writer stays usable */
            return -1;
        }
        if (w->format == FT_EV_EVT3 && (ev[i].x > 2047 || ev[i].y > 2047)) {
            wfail(w, "event %zu at (%u, %u): EVT 3.0 addresses are 11-bit", i, ev[i].x, ev[i].y);
            w->failed = 0;
            return -1;
        }
        last = ev[i].t;
    }
    if (w->format == FT_EV_EVT3) {
        if (n && !w->header_out && evt3_header(w, ev[0].t) < 0)
            return -1;
        return evt3_events(w, ev, n);
    }
    for (size_t i = 0; i < n; i += A4_MAX_PACKET) {
        size_t m = n - i < A4_MAX_PACKET ? n - i : A4_MAX_PACKET;
        if (a4_packet(w, ev + i, m) < 0)
            return -1;
    }
    w->last_t = last;
    return 0;
}

long long ft_ev_write_triggers(ft_ev_writer *w, const ft_ev_trigger *tr, size_t n) {
    if (w->failed)
        return -1;
    if (!w->triggers) {
        wfail(w, "this AEDAT 4.0 writer was opened without a trigger stream (FT_EV_W_TRIGGERS)");
        w->failed = 0;
        return -1;
    }
    /* What the format cannot hold is left out and counted: a negative time, or one before what
     * is already written (EVT 3.0: before the last event or trigger, a time the stream has passed;
     * AEDAT 4.0: before the last trigger, its stream being time-ordered), and on EVT 3.0 a channel
     * over its 4 bits. */
    long long dropped = 0;
    if (w->format == FT_EV_AEDAT4) {
        for (size_t i = 0; i < n;) {
            if (tq_reserve(w, A4_MAX_PACKET) < 0)
                return -1;
            size_t m = 0;
            for (; i < n && m < A4_MAX_PACKET; i++) {
                if (tr[i].t < 0 || tr[i].t < w->last_trig) {
                    dropped++;
                    continue;
                }
                w->tq[m++] = tr[i];
                w->last_trig = tr[i].t;
            }
            if (m && a4_trigger_packet(w, w->tq, m) < 0)
                return -1;
        }
        return dropped;
    }
    for (size_t i = 0; i < n; i++) {
        int64_t floor = w->last_t > w->last_trig ? w->last_t : w->last_trig;
        if (tr[i].t < 0 || tr[i].t < floor || tr[i].channel > 15 ||
            (w->header_out && tr[i].t < w->time_offset)) {
            dropped++;
            continue;
        }
        if (w->tq_n * sizeof *w->tq == w->tq_bytes &&
            tq_reserve(w, w->tq_n ? 2 * w->tq_n : 256) < 0) /* full: double */
            return -1;
        w->tq[w->tq_n++] = tr[i];
        w->last_trig = tr[i].t;
    }
    return dropped;
}

const char *ft_ev_writer_error(const ft_ev_writer *w) {
    return w->err;
}

int64_t ft_ev_writer_time_offset(const ft_ev_writer *w) {
    return w->time_offset;
}

int ft_ev_writer_close(ft_ev_writer *w, char *err, size_t err_len) {
    if (!w)
        return 0;
    if (w->format == FT_EV_EVT3 && !w->failed) {
        /* the header if no event came (its time from a held trigger, else 0), then the
         * triggers after the last event */
        if (!w->header_out)
            evt3_header(w, w->tq_n ? w->tq[w->tq_head].t : 0);
        if (!w->failed && evt3_triggers_upto(w, INT64_MAX) == 0)
            evt3_flush(w);
    }
    int rc = w->failed ? -1 : 0;
    if (fclose(w->f) != 0 && rc == 0) {
        wfail(w, "close error: %s", strerror(errno));
        rc = -1;
    }
    if (err && err_len)
        snprintf(err, err_len, "%s", rc < 0 ? w->err : "");
    free(w->pkt);
    free(w->comp);
    free(w->words);
    free(w->tq);
    free(w);
    return rc;
}
