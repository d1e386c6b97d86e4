/* Internals shared by the event-file readers (ev_reader.c: opening, headers, dispatch; ev_aedat.c
 * and ev_prophesee.c: the per-format decoders; ev_input.c: input buffer, errors, trigger times,
 * which all of them use). Calls go one way: ev_reader.c -> decoders -> ev_input.c. */
#ifndef FLYTRACK_EV_INTERNAL_H
#define FLYTRACK_EV_INTERNAL_H

#include <stdint.h>
#include <string.h>

#include "flytrack/events.h"

/* AEDAT 2.0 address layouts (jAER's chip classes decode their addresses differently). */
enum { FT_A2_DVS128 = 0, FT_A2_DAVIS = 1 };

/* A packet (AEDAT 3/4) larger than this is taken as corruption, not allocated. */
#define FT_EV_MAX_UNIT (256u << 20)
#define FT_EV_READ_CHUNK (1u << 20)

struct ft_ev_reader {
    /* input: a file descriptor, or caller memory (fd < 0) */
    int fd;
    const uint8_t *data; /* == buf for files, the caller's bytes for memory */
    uint8_t *buf;
    void *map; /* a regular file mapped whole (then fd's data is read through it, no buf) */
    size_t map_len;
    size_t buf_cap, start, end; /* unconsumed bytes are data[start..end) */
    uint64_t data_off;          /* file offset of data[0] */
    int eof;
    char name[128];

    ft_ev_info info;
    int failed;
    char err[420];
    long long err_off;

    /* time state */
    int64_t t_base;  /* added on counter wraps */
    uint32_t t_last; /* last raw counter value (AEDAT2, DAT) */
    uint32_t t_high; /* EVT2 / EVT3 high time bits */
    uint32_t t_low;  /* EVT3 */
    int have_t_high;
    uint16_t y, x_base; /* EVT3 */
    uint8_t pol;
    uint8_t a2_layout; /* AEDAT 2.0 address layout: FT_A2_DVS128 or FT_A2_DAVIS (from # AEChip:) */

    /* AEDAT 4.0 */
    int64_t table_pos; /* -1: read packets to the end of the file */
    int32_t ev_stream; /* stream id of the events (-1 until the first event packet) */
    uint8_t *dec;      /* decompressed packet */
    size_t dec_cap, dec_len;
    void *lz4_ctx, *zstd_ctx;
    /* AEDAT 3.1 / 4.0: events of the current packet not yet returned */
    const uint8_t *pend;
    size_t pend_n, pend_i;
    int pend_kind; /* 3: AEDAT 3.1 polarity (8 B), 4: AEDAT 4.0 (16 B) */
    int32_t pend_overflow;

    /* trigger times kept for ft_ev_triggers (keep_triggers set) */
    int keep_triggers;
    uint64_t not_trig; /* AEDAT 4.0: stream ids (< 64) seen to hold something else than triggers */
    ft_ev_trigger *trig;
    size_t trig_n, trig_cap;
};

static inline uint16_t ev_le16(const uint8_t *p) {
    return (uint16_t)(p[0] | (p[1] << 8));
}
static inline uint32_t ev_le32(const uint8_t *p) {
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}
static inline uint32_t ev_be32(const uint8_t *p) {
    return (uint32_t)p[3] | ((uint32_t)p[2] << 8) | ((uint32_t)p[1] << 16) | ((uint32_t)p[0] << 24);
}
static inline uint64_t ev_le64(const uint8_t *p) {
    return (uint64_t)ev_le32(p) | ((uint64_t)ev_le32(p + 4) << 32);
}

/* Stores one event as two 64-bit words (t; x | y << 16 | p << 32, the pad bytes zero). */
static inline void ev_put(ft_event *e, int64_t t, uint32_t x, uint32_t y, uint32_t p) {
    uint64_t rest = (uint64_t)(x & 0xFFFFu) | ((uint64_t)(y & 0xFFFFu) << 16) | ((uint64_t)p << 32);
    memcpy(&e->t, &t, 8);
    memcpy(&e->x, &rest, 8);
}

/* ev_input.c. Makes at least n unconsumed bytes available; 1 if so, 0 at the end of input (or on a
 * read error, which also marks the reader failed). May move data. */
int ev_need(ft_ev_reader *r, size_t n);
/* Marks the reader failed at the given file offset: "<name>: at byte N: <message>". */
void ev_fail(ft_ev_reader *r, uint64_t off, const char *fmt, ...)
    __attribute__((format(printf, 3, 4)));
static inline uint64_t ev_pos(const ft_ev_reader *r) {
    return r->data_off + r->start;
}

/* Counts one trigger / sync event and keeps its time when asked to (see ft_ev_keep_triggers). */
void ev_trigger(ft_ev_reader *r, int64_t t, unsigned value, unsigned channel);

/* Per-format decoders: fill out[n..cap) and return the new n; stop at the end of the available
 * bytes (the caller refills) or on damage (r->failed). cap - n >= 16 on entry. */
size_t ev_decode_aedat2(ft_ev_reader *r, ft_event *out, size_t n, size_t cap);
size_t ev_decode_evt2(ft_ev_reader *r, ft_event *out, size_t n, size_t cap);
size_t ev_decode_evt3(ft_ev_reader *r, ft_event *out, size_t n, size_t cap);
size_t ev_decode_dat(ft_ev_reader *r, ft_event *out, size_t n, size_t cap);
/* Packet formats: load the next packet into r->pend (return 1), 0 at the end, -1 on damage. */
int ev_next_packet_aedat3(ft_ev_reader *r);
int ev_next_packet_aedat4(ft_ev_reader *r);
int ev_aedat4_header(ft_ev_reader *r);
size_t ev_drain_pending(ft_ev_reader *r, ft_event *out, size_t n, size_t cap);
void ev_aedat4_free(ft_ev_reader *r);

#endif
