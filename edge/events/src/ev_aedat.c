/* AEDAT decoders (iniVation / jAER formats):
 * - 2.0: big-endian u32 address + u32 timestamp (us), the address laid out as the header's AEChip
 *   class has it. DVS128: x = 127 - bits 7..1 (jAER mirrors x), y = bits 14..8, raw bit 0 = 1 is
 *   OFF; bit 15 is an external sync event and bit 31 a special event (counted as triggers, not
 *   returned). DAVIS: see decode_davis.
 * - 3.1: packets of a 28-byte header (type, source, size, ts offset, ts overflow, capacity,
 *   number, valid) and capacity x size bytes; polarity events (type 1, 8 bytes): u32 data
 *   (bit 0 valid, bit 1 polarity, y bits 16..2, x bits 31..17) + i32 timestamp, whose high bits
 *   come from the packet's ts overflow (t = overflow << 31 | ts).
 * - 4.0: IOHeader FlatBuffer (compression, data-table position, info XML), then packets of
 *   i32 stream id + i32 size + (compressed) size-prefixed FlatBuffer; an "EVTS" packet's first
 *   field is a vector of 16-byte events (i64 t, i16 x, i16 y, u8 on, 3 pad); a "TRIG" packet's
 *   (read when trigger times are kept) a vector of Trigger tables (i64 timestamp, i8 type). */
#include <lz4frame.h>
#include <stdio.h>
#include <stdlib.h>
#include <zstd.h>

#include "ev_internal.h"

/* DAVIS layout (jAER's DavisChip constants and DavisBaseCamera's extractor): bit 31 clear is a DVS
 * word (bits 11..10 = 01: an external input event; else y bits 30..22, x bits 21..12 mirrored as
 * jAER shows it, polarity bit 11 = ON); bit 31 set is an APS (frame) sample, or an IMU sample word
 * when bits 11 and 10 are set too. Frames and IMU samples are not events here: they are counted as
 * skipped, like an address outside the chip's sensor. */
#define DAVIS_APS 0x80000000u
#define DAVIS_TYPE 0x00000C00u
#define DAVIS_EXTERNAL 0x00000400u

static size_t decode_davis(ft_ev_reader *r, ft_event *out, size_t n, size_t cap) {
    const uint8_t *p = r->data + r->start;
    size_t recs = (r->end - r->start) / 8, room = cap - n, i = 0;
    int64_t base = r->t_base;
    uint32_t last = r->t_last;
    uint32_t w = (uint32_t)r->info.width, h = (uint32_t)r->info.height;
    for (; i < recs && room > 0; i++) {
        uint32_t a = ev_be32(p + 8 * i), ts = ev_be32(p + 8 * i + 4);
        if (__builtin_expect(ts < last && last - ts > 0x80000000u, 0)) /* 32-bit us wrapped */
            base += (int64_t)1 << 32;
        last = ts;
        if (a & DAVIS_APS) { /* APS sample, or an IMU word (0x80000C00 all set) */
            r->info.n_skipped++;
            continue;
        }
        if ((a & DAVIS_TYPE) == DAVIS_EXTERNAL) {
            ev_trigger(r, base + ts, 1u, 0u);
            continue;
        }
        uint32_t xf = (a >> 12) & 0x3FFu, y = (a >> 22) & 0x1FFu;
        if (xf >= w || y >= h) { /* not a pixel of this chip: damage, or another chip's file */
            r->info.n_skipped++;
            continue;
        }
        ev_put(&out[n++], base + ts, w - 1u - xf, y, (a >> 11) & 1u);
        room--;
    }
    r->t_base = base;
    r->t_last = last;
    r->start += 8 * i;
    return n;
}

size_t ev_decode_aedat2(ft_ev_reader *r, ft_event *out, size_t n, size_t cap) {
    if (r->a2_layout == FT_A2_DAVIS)
        return decode_davis(r, out, n, cap);
    const uint8_t *p = r->data + r->start;
    size_t recs = (r->end - r->start) / 8, room = cap - n, i = 0;
    int64_t base = r->t_base; /* locals: stores to out could alias *r */
    uint32_t last = r->t_last;
    for (; i < recs && room > 0; i++) {
        uint32_t a = ev_be32(p + 8 * i), ts = ev_be32(p + 8 * i + 4);
        if (__builtin_expect(ts < last && last - ts > 0x80000000u, 0)) /* 32-bit us wrapped */
            base += (int64_t)1 << 32;
        last = ts;
        if (a & 0x80008000u) { /* external sync (bit 15) or special event (bit 31) */
            ev_trigger(r, base + ts, 1u, 0u);
            continue;
        }
        ev_put(&out[n++], base + ts, 127u - ((a >> 1) & 0x7Fu), (a >> 8) & 0x7Fu, ~a & 1u);
        room--;
    }
    r->t_base = base;
    r->t_last = last;
    r->start += 8 * i;
    return n;
}

/* ---- AEDAT 3.1 ------------------------------------------------------------------------------ */

#define A3_HEADER 28
#define A3_SPECIAL 0
#define A3_POLARITY 1

int ev_next_packet_aedat3(ft_ev_reader *r) {
    for (;;) {
        uint64_t at = ev_pos(r);
        if (!ev_need(r, A3_HEADER)) {
            if (r->end > r->start)
                ev_fail(r, at,
                        "truncated file: AEDAT 3.1 packet header cut short (%zu of 28 bytes)",
                        r->end - r->start);
            return r->failed ? -1 : 0;
        }
        const uint8_t *h = r->data + r->start;
        int type = (int16_t)ev_le16(h);
        int32_t size = (int32_t)ev_le32(h + 4), overflow = (int32_t)ev_le32(h + 12);
        int32_t capacity = (int32_t)ev_le32(h + 16), number = (int32_t)ev_le32(h + 20);
        if (size <= 0 || capacity < 0 || number < 0 || number > capacity ||
            (uint64_t)size * (uint64_t)capacity > FT_EV_MAX_UNIT) {
            ev_fail(r, at,
                    "corrupt AEDAT 3.1 packet header (type %d, event size %d, capacity %d, "
                    "number %d)",
                    type, size, capacity, number);
            return -1;
        }
        size_t bytes = (size_t)size * (size_t)capacity;
        if (!ev_need(r, A3_HEADER + bytes)) {
            ev_fail(r, at,
                    "truncated file: AEDAT 3.1 packet of %zu bytes cut short (%zu bytes left)",
                    A3_HEADER + bytes, r->end - r->start);
            return -1;
        }
        h = r->data + r->start;
        if (type == A3_POLARITY) {
            if (size != 8) {
                ev_fail(r, at, "AEDAT 3.1 polarity packet with %d-byte events (8 expected)", size);
                return -1;
            }
            /* copied: the input buffer may move before the packet is drained */
            if (r->dec_cap < bytes) {
                uint8_t *nb = realloc(r->dec, bytes);
                if (!nb) {
                    ev_fail(r, at, "out of memory for a packet of %zu bytes", bytes);
                    return -1;
                }
                r->dec = nb;
                r->dec_cap = bytes;
            }
            if (bytes)
                memcpy(r->dec, h + A3_HEADER, bytes);
            r->pend = r->dec;
            r->pend_n = (size_t)number;
            r->pend_i = 0;
            r->pend_kind = 3;
            r->pend_overflow = overflow;
            r->start += A3_HEADER + bytes;
            if (number > 0)
                return 1;
            continue;
        }
        if (type == A3_SPECIAL && size >= 8) { /* external input edges and pulses: types 2..4 */
            for (int32_t i = 0; i < number; i++) {
                const uint8_t *e = h + A3_HEADER + (size_t)i * (size_t)size;
                uint32_t d = ev_le32(e), ts = ev_le32(e + 4);
                uint32_t kind = (d >> 1) & 0x7Fu;
                /* 2 rising edge, 3 falling edge, 4 pulse; time as for polarity events */
                if ((d & 1u) && kind >= 2 && kind <= 4)
                    ev_trigger(r,
                               (int64_t)((uint64_t)(uint32_t)overflow << 31) |
                                   (int64_t)(ts & 0x7FFFFFFFu),
                               kind != 3, 0u);
            }
        } else {
            r->info.n_skipped++;
        }
        r->start += A3_HEADER + bytes;
    }
}

size_t ev_drain_pending(ft_ev_reader *r, ft_event *out, size_t n, size_t cap) {
    const uint8_t *p = r->pend;
    size_t i = r->pend_i;
    if (r->pend_kind == 4) {
        size_t take = r->pend_n - i < cap - n ? r->pend_n - i : cap - n;
        for (size_t k = 0; k < take; k++, i++) {
            const uint8_t *e = p + 16 * i;
            ev_put(&out[n++], (int64_t)ev_le64(e), ev_le16(e + 8), ev_le16(e + 10),
                   e[12] ? 1u : 0u);
        }
    } else {
        int64_t hi = (int64_t)((uint64_t)(uint32_t)r->pend_overflow << 31);
        for (; i < r->pend_n && n < cap; i++) {
            uint32_t d = ev_le32(p + 8 * i), ts = ev_le32(p + 8 * i + 4);
            if (!(d & 1u)) /* invalidated event */
                continue;
            ev_put(&out[n++], hi | (int64_t)(ts & 0x7FFFFFFFu), d >> 17, (d >> 2) & 0x7FFFu,
                   (d >> 1) & 1u);
        }
    }
    r->pend_i = i;
    return n;
}

/* ---- AEDAT 4.0 ------------------------------------------------------------------------------ */

/* Reads field `index` of the FlatBuffer table at `table` in b[0..len): its absolute offset, or 0
 * when absent; -1 when the table or its vtable lies outside the buffer. */
static long long fb_field(const uint8_t *b, size_t len, size_t table, int index, size_t width) {
    if (table + 4 > len)
        return -1;
    long long vt = (long long)table - (int32_t)ev_le32(b + table);
    if (vt < 0 || (size_t)vt + 4 > len)
        return -1;
    size_t vtsize = ev_le16(b + vt);
    if ((size_t)vt + vtsize > len)
        return -1;
    size_t slot = 4 + 2 * (size_t)index;
    if (slot + 2 > vtsize)
        return 0;
    size_t fo = ev_le16(b + vt + slot);
    if (!fo)
        return 0;
    if (table + fo + width > len)
        return -1;
    return (long long)(table + fo);
}

static int xml_int(const char *xml, size_t len, const char *key, int *out) {
    char pat[32];
    snprintf(pat, sizeof pat, "key=\"%s\"", key);
    size_t pl = strlen(pat);
    for (size_t i = 0; i + pl < len; i++) {
        if (memcmp(xml + i, pat, pl) == 0) {
            const char *gt = memchr(xml + i, '>', len - i);
            if (!gt)
                return 0;
            long v = 0;
            size_t k = (size_t)(gt - xml) + 1;
            int any = 0;
            while (k < len && xml[k] >= '0' && xml[k] <= '9' && v < 1000000) {
                v = v * 10 + (xml[k++] - '0');
                any = 1;
            }
            if (any)
                *out = (int)v;
            return any;
        }
    }
    return 0;
}

int ev_aedat4_header(ft_ev_reader *r) {
    /* the version line */
    if (!ev_need(r, 14)) {
        ev_fail(r, 0, "AEDAT 4.0 file ends in its version line");
        return -1;
    }
    const uint8_t *p = r->data + r->start;
    r->start += (p[12] == '\r' && p[13] == '\n') ? 14 : (p[12] == '\n' ? 13 : 0);
    if (r->start == 0) {
        ev_fail(r, 12, "AEDAT 4.0 version line not ended by a newline");
        return -1;
    }
    uint64_t at = ev_pos(r);
    if (!ev_need(r, 4)) {
        ev_fail(r, at, "AEDAT 4.0 file ends before its header size");
        return -1;
    }
    uint32_t hsize = ev_le32(r->data + r->start);
    if (hsize < 8 || hsize > (64u << 20)) {
        ev_fail(r, at, "AEDAT 4.0 header size %u out of range", hsize);
        return -1;
    }
    if (!ev_need(r, 4 + (size_t)hsize)) {
        ev_fail(r, at, "truncated file: AEDAT 4.0 header of %u bytes cut short", hsize);
        return -1;
    }
    const uint8_t *b = r->data + r->start + 4;
    size_t table = ev_le32(b);
    long long f_comp = fb_field(b, hsize, table, 0, 4);
    long long f_pos = fb_field(b, hsize, table, 1, 8);
    long long f_info = fb_field(b, hsize, table, 2, 4);
    if (f_comp < 0 || f_pos < 0 || f_info < 0) {
        ev_fail(r, at + 4, "corrupt AEDAT 4.0 IOHeader (FlatBuffer table outside its %u bytes)",
                hsize);
        return -1;
    }
    r->info.compression = f_comp ? (int32_t)ev_le32(b + f_comp) : 0;
    if (r->info.compression < 0 || r->info.compression > FT_EV_COMP_ZSTD_HIGH) {
        ev_fail(r, at + 4 + (uint64_t)f_comp, "unknown AEDAT 4.0 compression type %d",
                r->info.compression);
        return -1;
    }
    r->table_pos = f_pos ? (int64_t)ev_le64(b + f_pos) : -1;
    if (f_info) {
        size_t s = (size_t)f_info + ev_le32(b + f_info);
        if (s + 4 <= hsize) {
            size_t sl = ev_le32(b + s);
            if (sl <= hsize - s - 4) {
                xml_int((const char *)b + s + 4, sl, "sizeX", &r->info.width);
                xml_int((const char *)b + s + 4, sl, "sizeY", &r->info.height);
            }
        }
    }
    r->start += 4 + (size_t)hsize;
    return 0;
}

static int grow_dec(ft_ev_reader *r, size_t want, uint64_t at) {
    if (want <= r->dec_cap)
        return 0;
    if (want > FT_EV_MAX_UNIT) {
        ev_fail(r, at, "AEDAT 4.0 packet decompresses to more than %u bytes", FT_EV_MAX_UNIT);
        return -1;
    }
    size_t cap = r->dec_cap ? r->dec_cap : 65536;
    while (cap < want)
        cap *= 2;
    uint8_t *nb = realloc(r->dec, cap);
    if (!nb) {
        ev_fail(r, at, "out of memory for a packet of %zu bytes", cap);
        return -1;
    }
    r->dec = nb;
    r->dec_cap = cap;
    return 0;
}

static int decompress(ft_ev_reader *r, const uint8_t *src, size_t len, uint64_t at) {
    int comp = r->info.compression;
    r->dec_len = 0;
    if (comp == FT_EV_COMP_NONE) {
        if (grow_dec(r, len, at) < 0)
            return -1;
        memcpy(r->dec, src, len);
        r->dec_len = len;
        return 0;
    }
    if (comp == FT_EV_COMP_LZ4 || comp == FT_EV_COMP_LZ4_HIGH) {
        if (!r->lz4_ctx &&
            LZ4F_isError(LZ4F_createDecompressionContext((LZ4F_dctx **)&r->lz4_ctx, LZ4F_VERSION)))
            r->lz4_ctx = NULL;
        if (!r->lz4_ctx) {
            ev_fail(r, at, "cannot create an LZ4 context");
            return -1;
        }
        LZ4F_resetDecompressionContext(r->lz4_ctx);
        for (;;) {
            if (r->dec_cap - r->dec_len < 65536 && grow_dec(r, r->dec_len + 65536, at) < 0)
                return -1;
            size_t dst = r->dec_cap - r->dec_len, used = len;
            size_t ret = LZ4F_decompress(r->lz4_ctx, r->dec + r->dec_len, &dst, src, &used, NULL);
            if (LZ4F_isError(ret)) {
                ev_fail(r, at, "corrupt LZ4 frame in an AEDAT 4.0 packet (%s)",
                        LZ4F_getErrorName(ret));
                return -1;
            }
            r->dec_len += dst;
            src += used;
            len -= used;
            if (ret == 0)
                return 0;
            if (len == 0 && dst == 0) {
                ev_fail(r, at, "LZ4 frame of an AEDAT 4.0 packet cut short");
                return -1;
            }
        }
    }
    if (!r->zstd_ctx)
        r->zstd_ctx = ZSTD_createDCtx();
    if (!r->zstd_ctx) {
        ev_fail(r, at, "cannot create a Zstd context");
        return -1;
    }
    ZSTD_DCtx_reset(r->zstd_ctx, ZSTD_reset_session_only);
    ZSTD_inBuffer in = {src, len, 0};
    for (;;) {
        if (r->dec_cap - r->dec_len < 65536 && grow_dec(r, r->dec_len + 65536, at) < 0)
            return -1;
        ZSTD_outBuffer o = {r->dec + r->dec_len, r->dec_cap - r->dec_len, 0};
        size_t ret = ZSTD_decompressStream(r->zstd_ctx, &o, &in);
        if (ZSTD_isError(ret)) {
            ev_fail(r, at, "corrupt Zstd frame in an AEDAT 4.0 packet (%s)",
                    ZSTD_getErrorName(ret));
            return -1;
        }
        r->dec_len += o.pos;
        if (ret == 0)
            return 0;
        if (in.pos == in.size && o.pos < o.size) {
            ev_fail(r, at, "Zstd frame of an AEDAT 4.0 packet cut short");
            return -1;
        }
    }
}

/* A TriggerPacket (identifier "TRIG", dv's trigger stream): a table whose field 0 is a vector of
 * Trigger tables {timestamp: int64 (field 0), type: int8 (field 1)}; the external signal's rising
 * edges (type 1), falling edges (2) and pulses (3) are kept. 1: it was one; 0: another kind of
 * packet; -1: corrupt (the reader failed). */
static int aedat4_triggers(ft_ev_reader *r, const uint8_t *b, size_t len, uint64_t at) {
    if (len >= 12 && memcmp(b + 8, "TRIG", 4) == 0 && ev_le32(b) <= len - 4) {
        len = ev_le32(b); /* size-prefixed */
        b += 4;
    } else if (!(len >= 8 && memcmp(b + 4, "TRIG", 4) == 0)) {
        return 0;
    }
    long long f = fb_field(b, len, ev_le32(b), 0, 4);
    if (f < 0)
        goto corrupt;
    if (f == 0)
        return 1;
    uint64_t vec = (uint64_t)f + ev_le32(b + f);
    if (vec + 4 > len)
        goto corrupt;
    uint64_t count = ev_le32(b + vec);
    if (count > (len - vec - 4) / 4)
        goto corrupt;
    for (uint64_t i = 0; i < count; i++) {
        uint64_t slot = vec + 4 + 4 * i;
        uint64_t el = slot + ev_le32(b + slot);
        if (el + 4 > len)
            goto corrupt;
        long long ft = fb_field(b, len, (size_t)el, 0, 8), fk = fb_field(b, len, (size_t)el, 1, 1);
        if (ft < 0 || fk < 0)
            goto corrupt;
        int kind = fk ? (int8_t)b[fk] : 0;
        if (kind >= 1 && kind <= 3)
            ev_trigger(r, ft ? (int64_t)ev_le64(b + ft) : 0, kind != 2, 0u);
    }
    return 1;
corrupt:
    ev_fail(r, at, "corrupt AEDAT 4.0 trigger packet (FlatBuffer outside its %zu bytes)", len);
    return -1;
}

int ev_next_packet_aedat4(ft_ev_reader *r) {
    for (;;) {
        uint64_t at = ev_pos(r);
        if (r->table_pos >= 0 && at >= (uint64_t)r->table_pos)
            return 0; /* the data table (an index) follows the last packet */
        if (!ev_need(r, 8)) {
            if (r->end > r->start || r->table_pos >= 0)
                ev_fail(r, at,
                        "truncated file: AEDAT 4.0 packet header cut short (%zu of 8 "
                        "bytes, data table expected at %lld)",
                        r->end - r->start, (long long)r->table_pos);
            return r->failed ? -1 : 0;
        }
        const uint8_t *h = r->data + r->start;
        int32_t stream = (int32_t)ev_le32(h), size = (int32_t)ev_le32(h + 4);
        if (stream < 0 || size <= 0 || (uint32_t)size > FT_EV_MAX_UNIT) {
            ev_fail(r, at, "corrupt AEDAT 4.0 packet header (stream %d, size %d)", stream, size);
            return -1;
        }
        if (!ev_need(r, 8 + (size_t)size)) {
            ev_fail(r, at,
                    "truncated file: AEDAT 4.0 packet of %d bytes cut short (%zu bytes left)", size,
                    r->end - r->start - 8);
            return -1;
        }
        if (r->ev_stream >= 0 && stream != r->ev_stream) {
            /* another stream: frames, IMU, triggers, a second camera; triggers are decoded when
             * kept (a stream whose first packet was something else is not looked into again) */
            int known_other = stream < 64 && ((r->not_trig >> stream) & 1u);
            if (r->keep_triggers && !known_other) {
                if (decompress(r, r->data + r->start + 8, (size_t)size, at) < 0)
                    return -1;
                int k = aedat4_triggers(r, r->dec, r->dec_len, at);
                if (k < 0)
                    return -1;
                if (k == 0 && stream < 64)
                    r->not_trig |= (uint64_t)1 << stream;
                if (k == 0)
                    r->info.n_skipped++;
            } else {
                r->info.n_skipped++;
            }
            r->start += 8 + (size_t)size;
            continue;
        }
        if (decompress(r, r->data + r->start + 8, (size_t)size, at) < 0)
            return -1;
        r->start += 8 + (size_t)size;
        const uint8_t *b = r->dec;
        size_t len = r->dec_len;
        if (len >= 12 && memcmp(b + 8, "EVTS", 4) == 0 && ev_le32(b) <= len - 4) {
            len = ev_le32(b); /* size-prefixed, as dv writes them */
            b += 4;
        } else if (!(len >= 8 && memcmp(b + 4, "EVTS", 4) == 0)) {
            if (r->ev_stream >= 0) {
                ev_fail(r, at, "AEDAT 4.0 event packet (stream %d) without its EVTS identifier",
                        stream);
                return -1;
            }
            int k = r->keep_triggers ? aedat4_triggers(r, r->dec, r->dec_len, at) : 0;
            if (k < 0)
                return -1;
            if (k == 0)
                r->info.n_skipped++; /* not an event stream */
            continue;
        }
        r->ev_stream = stream;
        size_t table = ev_le32(b);
        long long f = fb_field(b, len, table, 0, 4);
        if (f < 0) {
            ev_fail(r, at,
                    "corrupt AEDAT 4.0 event packet (FlatBuffer table outside its %zu "
                    "bytes)",
                    len);
            return -1;
        }
        if (f == 0)
            continue; /* no events */
        uint64_t vec = (uint64_t)f + ev_le32(b + f);
        if (vec + 4 > len) {
            ev_fail(r, at, "corrupt AEDAT 4.0 event packet (event vector outside the packet)");
            return -1;
        }
        uint64_t count = ev_le32(b + vec);
        if (count > (len - vec - 4) / 16) {
            ev_fail(r, at, "corrupt AEDAT 4.0 event packet (%llu events do not fit its %zu bytes)",
                    (unsigned long long)count, len);
            return -1;
        }
        r->pend = b + vec + 4;
        r->pend_n = (size_t)count;
        r->pend_i = 0;
        r->pend_kind = 4;
        if (count)
            return 1;
    }
}

void ev_aedat4_free(ft_ev_reader *r) {
    if (r->lz4_ctx)
        LZ4F_freeDecompressionContext(r->lz4_ctx);
    if (r->zstd_ctx)
        ZSTD_freeDCtx(r->zstd_ctx);
    free(r->dec);
    r->lz4_ctx = r->zstd_ctx = NULL;
    r->dec = NULL;
}
