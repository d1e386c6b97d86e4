/* Prophesee decoders: EVT 2.0 (32-bit words), EVT 3.0 (16-bit stateful words) and DAT (8-byte CD
 * events). Formats as Prophesee documents them (Metavision "Event data formats"). */
#include "ev_internal.h"

/* EVT 2.0 word types (bits 31..28) */
#define EVT2_CD_OFF 0x0u
#define EVT2_CD_ON 0x1u
#define EVT2_TIME_HIGH 0x8u
#define EVT2_EXT_TRIGGER 0xAu

size_t ev_decode_evt2(ft_ev_reader *r, ft_event *out, size_t n, size_t cap) {
    const uint8_t *p = r->data + r->start;
    size_t words = (r->end - r->start) / 4, room = cap - n;
    size_t i = 0;
    int64_t t_hi = r->t_base + ((int64_t)r->t_high << 6);
    for (; i < words && room > 0; i++) {
        uint32_t w = ev_le32(p + 4 * i);
        uint32_t type = w >> 28;
        if (type <= EVT2_CD_ON) {
            ev_put(&out[n++], t_hi | (int64_t)((w >> 22) & 0x3Fu), (w >> 11) & 0x7FFu, w & 0x7FFu,
                   type);
            room--;
        } else if (type == EVT2_TIME_HIGH) {
            uint32_t th = w & 0x0FFFFFFFu;
            if (r->have_t_high && th < r->t_high) /* the 34-bit time wrapped (~4.8 h) */
                r->t_base += (int64_t)1 << 34;
            r->t_high = th;
            r->have_t_high = 1;
            t_hi = r->t_base + ((int64_t)th << 6);
        } else if (type == EVT2_EXT_TRIGGER) {
            /* bits 27..22 time low, 12..8 channel id, 0 edge value */
            ev_trigger(r, t_hi | (int64_t)((w >> 22) & 0x3Fu), w & 1u, (w >> 8) & 0x1Fu);
        } else {
            r->info.n_skipped++; /* OTHERS, CONTINUED, undefined */
        }
    }
    r->start += 4 * i;
    return n;
}

/* EVT 3.0 word types (bits 15..12) */
#define EVT3_ADDR_Y 0x0u
#define EVT3_ADDR_X 0x2u
#define EVT3_VECT_BASE_X 0x3u
#define EVT3_VECT_12 0x4u
#define EVT3_VECT_8 0x5u
#define EVT3_TIME_LOW 0x6u
#define EVT3_TIME_HIGH 0x8u
#define EVT3_EXT_TRIGGER 0xAu

/* Word types the fast path handles without a branch on the type: ADDR_Y, ADDR_X, TIME_LOW (most
 * words of a stream); every other type takes the switch. */
#define EVT3_SLOW_TYPES (~((1u << EVT3_ADDR_Y) | (1u << EVT3_ADDR_X) | (1u << EVT3_TIME_LOW)))

size_t ev_decode_evt3(ft_ev_reader *r, ft_event *out, size_t n, size_t cap) {
    const uint8_t *p = r->data + r->start;
    size_t words = (r->end - r->start) / 2, i = 0;
    uint32_t y = r->y, xb = r->x_base, tl = r->t_low;
    uint8_t pol = r->pol;
    int64_t hi = r->t_base + ((int64_t)r->t_high << 12);
    /* stop with room for one more VECT_12 (12 events) */
    for (; i < words && n + 12 < cap; i++) {
        uint32_t w = ev_le16(p + 2 * i), type = w >> 12;
        if (!((EVT3_SLOW_TYPES >> type) & 1u)) {
            /* ADDR_Y / ADDR_X / TIME_LOW: select instead of branching (the order of these types
             * is data-dependent, so a branch on it mispredicts); the event slot is written every
             * time and kept only for ADDR_X. */
            uint32_t v = w & 0x7FFu;
            y = type == EVT3_ADDR_Y ? v : y;
            tl = type == EVT3_TIME_LOW ? (w & 0xFFFu) : tl;
            ev_put(&out[n], hi + tl, v, y, (w >> 11) & 1u);
            n += type == EVT3_ADDR_X;
            continue;
        }
        switch (type) {
        case EVT3_VECT_BASE_X:
            xb = w & 0x7FFu;
            pol = (uint8_t)((w >> 11) & 1u);
            break;
        case EVT3_VECT_12:
        case EVT3_VECT_8: {
            uint32_t m = type == EVT3_VECT_12 ? (w & 0xFFFu) : (w & 0xFFu);
            while (m) {
                int b = __builtin_ctz(m);
                ev_put(&out[n++], hi + tl, xb + (uint32_t)b, y, pol);
                m &= m - 1;
            }
            xb = (xb + (type == EVT3_VECT_12 ? 12u : 8u)) & 0xFFFFu;
            break;
        }
        case EVT3_TIME_HIGH: {
            uint32_t th = w & 0xFFFu;
            if (r->have_t_high && th < r->t_high) /* the 24-bit time wrapped (16.7 s) */
                r->t_base += (int64_t)1 << 24;
            r->t_high = th;
            r->have_t_high = 1;
            hi = r->t_base + ((int64_t)th << 12);
            break;
        }
        case EVT3_EXT_TRIGGER: /* bits 11..8 channel id, 0 edge value */
            ev_trigger(r, hi + tl, w & 1u, (w >> 8) & 0xFu);
            break;
        default: /* CONTINUED_4, OTHERS, CONTINUED_12, undefined */
            r->info.n_skipped++;
            break;
        }
    }
    r->y = (uint16_t)y;
    r->x_base = (uint16_t)xb;
    r->pol = pol;
    r->t_low = tl;
    r->start += 2 * i;
    return n;
}

size_t ev_decode_dat(ft_ev_reader *r, ft_event *out, size_t n, size_t cap) {
    const uint8_t *p = r->data + r->start;
    size_t recs = (r->end - r->start) / 8, room = cap - n, i = 0;
    /* the time state in locals: stores to out could alias *r, which would reload it per event */
    int64_t base = r->t_base;
    uint32_t last = r->t_last;
    for (; i < recs && i < room; i++) {
        uint32_t ts = ev_le32(p + 8 * i), d = ev_le32(p + 8 * i + 4);
        if (__builtin_expect(ts < last && last - ts > 0x80000000u, 0)) /* 32-bit us wrapped */
            base += (int64_t)1 << 32;
        last = ts;
        ev_put(&out[n++], base + ts, d & 0x3FFFu, (d >> 14) & 0x3FFFu, (d >> 28) ? 1u : 0u);
    }
    r->t_base = base;
    r->t_last = last;
    r->start += 8 * i;
    return n;
}
