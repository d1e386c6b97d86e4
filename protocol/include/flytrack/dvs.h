/* FlyTrack DVS128 USB event words (protocol/SPEC.md section 2) and a running decoder that turns
 * them into events with a 64-bit microsecond time.
 *
 * Header-only C99, no allocation, no float. A word keeps all its bits (also x, y and polarity of
 * RESET/WRAP words, which carry no meaning) so that decoding then encoding gives the same bytes.
 */
#ifndef FLYTRACK_DVS_H
#define FLYTRACK_DVS_H

#include "wire.h"

#define FT_DVS_WORD_SIZE 4
#define FT_DVS_TS_BITS 14
#define FT_DVS_TS_MASK 0x3FFFu
#define FT_DVS_RESET_BIT 0x4000u
#define FT_DVS_WRAP_BIT 0x8000u
#define FT_DVS_WRAP_US 0x4000u
#define FT_DVS_SYNC_BIT 0x80u /* in byte 1: an external-input (sync) event */

#define FT_DVS_EVENT 0 /* an address event */
#define FT_DVS_RESET 1 /* the device zeroed its timestamp counter */
#define FT_DVS_WRAP 2  /* the 14-bit counter wrapped */
#define FT_DVS_SYNC 3  /* an external-input (sync) event at ts: the bridge's frame-pulse input */

typedef struct {
    uint8_t kind;     /* FT_DVS_EVENT, FT_DVS_RESET, FT_DVS_WRAP, FT_DVS_SYNC */
    uint8_t x;        /* 0..127 */
    uint8_t y;        /* 0..127 */
    uint8_t polarity; /* 1 = ON (brighter) */
    uint16_t ts;      /* 14-bit timestamp, us */
} ft_dvs_word;

typedef struct {
    uint64_t t_us; /* offset + ts */
    uint8_t x, y, polarity;
} ft_dvs_event;

/* BAD_FIELD if RESET and WRAP are both set, or SYNC (byte 1, bit 7) is set on a RESET or WRAP word.
 */
static inline ft_err ft_dvs_word_decode(const uint8_t *p, ft_dvs_word *w) {
    uint16_t t = ft_ld_u16(p + 2);
    /* *w is filled also on error */
    w->x = (uint8_t)(p[0] >> 1);
    w->polarity = (uint8_t)(p[0] & 1u);
    w->y = (uint8_t)(p[1] & 0x7Fu);
    w->ts = (uint16_t)(t & FT_DVS_TS_MASK);
    w->kind = (t & FT_DVS_RESET_BIT)     ? FT_DVS_RESET
              : (t & FT_DVS_WRAP_BIT)    ? FT_DVS_WRAP
              : (p[1] & FT_DVS_SYNC_BIT) ? FT_DVS_SYNC
                                         : FT_DVS_EVENT;
    if ((t & FT_DVS_RESET_BIT) && (t & FT_DVS_WRAP_BIT))
        return FT_E_BAD_FIELD;
    if ((p[1] & FT_DVS_SYNC_BIT) && (t & (FT_DVS_RESET_BIT | FT_DVS_WRAP_BIT)))
        return FT_E_BAD_FIELD;
    return FT_OK;
}

/* BAD_FIELD for x, y > 127, polarity > 1, ts > 0x3FFF or an unknown kind. */
static inline ft_err ft_dvs_word_encode(uint8_t *p, const ft_dvs_word *w) {
    uint16_t t;
    if (w->x > 127 || w->y > 127 || w->polarity > 1 || w->ts > FT_DVS_TS_MASK ||
        w->kind > FT_DVS_SYNC)
        return FT_E_BAD_FIELD;
    t = w->ts;
    if (w->kind == FT_DVS_RESET)
        t |= FT_DVS_RESET_BIT;
    else if (w->kind == FT_DVS_WRAP)
        t |= FT_DVS_WRAP_BIT;
    p[0] = (uint8_t)((w->x << 1) | w->polarity);
    p[1] = (uint8_t)(w->y | (w->kind == FT_DVS_SYNC ? FT_DVS_SYNC_BIT : 0u));
    ft_st_u16(p + 2, t);
    return FT_OK;
}

/* Checks a whole USB packet: TRUNCATED if its size is not a multiple of 4, else the first bad
 * word's error. *n_events counts the address events in it (not SYNC words). */
static inline ft_err ft_dvs_packet_check(const uint8_t *buf, size_t len, size_t *n_events) {
    size_t i;
    ft_dvs_word w;
    *n_events = 0;
    if (len % FT_DVS_WORD_SIZE)
        return FT_E_TRUNCATED;
    for (i = 0; i < len; i += FT_DVS_WORD_SIZE) {
        if (ft_dvs_word_decode(buf + i, &w) != FT_OK)
            return FT_E_BAD_FIELD;
        if (w.kind == FT_DVS_EVENT)
            (*n_events)++;
    }
    return FT_OK;
}

/* The running decoder: t = offset + ts, offset += 0x4000 per WRAP, 0 after RESET. A SYNC word's
 * time goes to sync_t_us, and n_sync counts them. */
typedef struct {
    uint64_t offset;
    uint64_t sync_t_us;
    uint32_t n_sync;
} ft_dvs_decoder;

static inline void ft_dvs_decoder_init(ft_dvs_decoder *d) {
    d->offset = 0;
    d->sync_t_us = 0;
    d->n_sync = 0;
}

/* Applies one decoded word; returns 1 and fills *ev for an address event, else 0 (a SYNC word: 0,
 * with d->sync_t_us set and d->n_sync counted). */
static inline int ft_dvs_apply(ft_dvs_decoder *d, const ft_dvs_word *w, ft_dvs_event *ev) {
    if (w->kind == FT_DVS_RESET) {
        d->offset = 0;
        return 0;
    }
    if (w->kind == FT_DVS_WRAP) {
        d->offset += FT_DVS_WRAP_US;
        return 0;
    }
    if (w->kind == FT_DVS_SYNC) {
        d->sync_t_us = d->offset + w->ts;
        d->n_sync++;
        return 0;
    }
    ev->t_us = d->offset + w->ts;
    ev->x = w->x;
    ev->y = w->y;
    ev->polarity = w->polarity;
    return 1;
}

/* Decodes a whole USB packet into events (ev has room for cap). All or nothing: the packet is
 * checked first (TRUNCATED, BAD_FIELD; NO_SPACE if it holds more than cap events) and the decoder
 * state changes only when it is accepted. */
static inline ft_err ft_dvs_decode_packet(ft_dvs_decoder *d, const uint8_t *buf, size_t len,
                                          ft_dvs_event *ev, size_t cap, size_t *n_events) {
    size_t i, n = 0;
    ft_dvs_word w;
    ft_err e = ft_dvs_packet_check(buf, len, n_events);
    if (e != FT_OK)
        return e;
    if (*n_events > cap)
        return FT_E_NO_SPACE;
    for (i = 0; i < len; i += FT_DVS_WORD_SIZE) {
        ft_dvs_word_decode(buf + i, &w);
        n += (size_t)ft_dvs_apply(d, &w, &ev[n]);
    }
    return FT_OK;
}

#endif /* FLYTRACK_DVS_H */
