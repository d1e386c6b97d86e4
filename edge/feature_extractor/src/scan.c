/* The per-frame candidate scan: the hot loop of libflytrack_features.
 *
 * It rules pixels out coarse to fine, reading the frame alone while it can:
 *  1. the brightest and darkest pixels of a band of FT_BAND rows against the band's bounds (the
 *     lowest hi and the highest lo over it): a vector max/min and one compare at the end, about the
 *     cost of reading the rows;
 *  2. if the band fails (a candidate, or a background that varies a lot along it), each block of
 *     FT_BLOCK pixels of the band's rows at once against the band's bounds for that block, a bit
 *     per block, then each failing block row by row against the row's bounds for it;
 *  3. in a block that still cannot be ruled out, every pixel against its own hi and lo, as a 64-bit
 *     mask of candidates.
 * The masks are turned into runs of candidates (one row, consecutive x), and each candidate's
 * difference to the background is stored: regions are then labelled run by run and measured from
 * these arrays (regions.c), never from the frame again.
 *
 * Vector code: AVX-512BW or AVX2 intrinsics when compiled for them, else GCC vector extensions
 * (SSE on a portable x86 build, NEON on the ARM edge computers). The portable x86 build compiles
 * this file three times: once as itself (the baseline path and the choice of path) and once per
 * wider path with FT_SCAN_VARIANT defined (scan_avx2.c, scan_avx512bw.c, built for the x86-64
 * levels v3 and v4: AVX2, AVX-512); each compile defines its path as ft_fx_scan_<path>, and
 * ft_fx_create takes the widest this CPU runs (ft_fx_scan_select), so one binary runs on old CPUs
 * and is fast on new ones. scalar_scan selects the plain per-pixel loop instead: the tests check
 * that every path gives bit-identical results.
 */
#include "fx_internal.h"

#include <math.h>
#include <string.h>
#if defined(__AVX512BW__) || defined(__AVX2__)
#include <immintrin.h>
#endif

/* ---------------------------------------------------------------------------------------------- */
/* Vector kit: load, unsigned max/min, and "some lane of a above b" / "below b" tests */

#if defined(__AVX512BW__)
#define FT_PATH avx512bw
typedef __m512i vec;
#define VB 64
static inline vec ld(const void *p) {
    return _mm512_loadu_si512(p);
}
#define MAX8 _mm512_max_epu8
#define MIN8 _mm512_min_epu8
#define MAX16 _mm512_max_epu16
#define MIN16 _mm512_min_epu16
#define SET8(v) _mm512_set1_epi8((char)(v))
#define SET16(v) _mm512_set1_epi16((short)(v))
#define ANY_GT8(a, b) (_mm512_cmpgt_epu8_mask(a, b) != 0)
#define ANY_LT8(a, b) (_mm512_cmplt_epu8_mask(a, b) != 0)
#define ANY_GT16(a, b) (_mm512_cmpgt_epu16_mask(a, b) != 0)
#define ANY_LT16(a, b) (_mm512_cmplt_epu16_mask(a, b) != 0)
#elif defined(__AVX2__)
#define FT_PATH avx2
typedef __m256i vec;
#define VB 32
static inline vec ld(const void *p) {
    return _mm256_loadu_si256((const __m256i *)p);
}
#define MAX8 _mm256_max_epu8
#define MIN8 _mm256_min_epu8
#define MAX16 _mm256_max_epu16
#define MIN16 _mm256_min_epu16
#define SET8(v) _mm256_set1_epi8((char)(v))
#define SET16(v) _mm256_set1_epi16((short)(v))
/* Unsigned a > b somewhere <=> max(a, b) != b somewhere; a < b <=> min(a, b) != b. */
#define NE_ANY(x, b) (_mm256_movemask_epi8(_mm256_cmpeq_epi8(x, b)) != -1)
#define NE_ANY16(x, b) (_mm256_movemask_epi8(_mm256_cmpeq_epi16(x, b)) != -1)
#define ANY_GT8(a, b) NE_ANY(_mm256_max_epu8(a, b), b)
#define ANY_LT8(a, b) NE_ANY(_mm256_min_epu8(a, b), b)
#define ANY_GT16(a, b) NE_ANY16(_mm256_max_epu16(a, b), b)
#define ANY_LT16(a, b) NE_ANY16(_mm256_min_epu16(a, b), b)
#else
#define FT_PATH generic
/* GCC vector extensions: the compiler picks the target's instructions (SSE2, NEON, ...); 16 bytes
 * is their register width. */
#define VB 16
typedef uint8_t vec __attribute__((vector_size(VB)));
typedef uint16_t vec16 __attribute__((vector_size(VB)));
typedef uint64_t vec64 __attribute__((vector_size(VB)));
static inline vec ld(const void *p) {
    vec v;
    memcpy(&v, p, sizeof v);
    return v;
}
static inline int any_set(vec64 a) {
    uint64_t o = 0;
    for (unsigned i = 0; i < VB / 8; i++)
        o |= a[i];
    return o != 0;
}
static inline vec sel8(vec m, vec a, vec b) {
    return (a & m) | (b & ~m);
}
static inline vec sel16(vec16 m, vec a, vec b) {
    return (a & (vec)m) | (b & ~(vec)m);
}
#define MAX8(a, b) sel8((vec)((a) > (b)), a, b)
#define MIN8(a, b) sel8((vec)((a) < (b)), a, b)
#define MAX16(a, b) sel16((vec16)((vec16)(a) > (vec16)(b)), a, b)
#define MIN16(a, b) sel16((vec16)((vec16)(a) < (vec16)(b)), a, b)
#define SET8(v) ((vec){0} + (uint8_t)(v))
#define SET16(v) ((vec)((vec16){0} + (uint16_t)(v)))
#define ANY_GT8(a, b) any_set((vec64)((a) > (b)))
#define ANY_LT8(a, b) any_set((vec64)((a) < (b)))
#define ANY_GT16(a, b) any_set((vec64)((vec16)(a) > (vec16)(b)))
#define ANY_LT16(a, b) any_set((vec64)((vec16)(a) < (vec16)(b)))
#endif

/* This compile's names: ft_fx_scan8_<path> etc. (the objdump check in tests/check_isa.sh allows
 * wide instructions in functions so named only). */
#define FT_CAT_(a, b) a##_##b
#define FT_CAT(a, b) FT_CAT_(a, b)
#define FT_STR_(a) #a
#define FT_STR(a) FT_STR_(a)
#define FT_NAME(n) FT_CAT(n, FT_PATH)

/* Some pixel of r[0 .. n - 1] above h or below l. Rows shorter than a vector go pixel by pixel.
 * Otherwise the first vector is read where the row starts and the rest from the next vector-aligned
 * address on (a load that straddles two cache lines costs two), the last one ending where the row
 * ends: they overlap, which max and min do not mind. */
#define DEFINE_OUT(NAME, T, MAX, MIN, SET, ANY_GT, ANY_LT)                                         \
    static inline int NAME(const T *r, size_t n, T h, T l) {                                       \
        const size_t nl = VB / sizeof(T);                                                          \
        if (n < nl) {                                                                              \
            int out = 0;                                                                           \
            for (size_t x = 0; x < n; x++)                                                         \
                out |= (r[x] > h) | (r[x] < l);                                                    \
            return out;                                                                            \
        }                                                                                          \
        const T *e = r + n, *q = (const T *)(((uintptr_t)r + VB) & ~(uintptr_t)(VB - 1));          \
        vec mx = ld(r), mn = mx, mx2 = mx, mn2 = mx;                                               \
        for (; q + 2 * nl <= e; q += 2 * nl) { /* two pairs of accumulators: two loads a step */   \
            vec v = ld(__builtin_assume_aligned(q, VB)),                                           \
                u = ld(__builtin_assume_aligned(q + nl, VB));                                      \
            mx = MAX(mx, v);                                                                       \
            mn = MIN(mn, v);                                                                       \
            mx2 = MAX(mx2, u);                                                                     \
            mn2 = MIN(mn2, u);                                                                     \
        }                                                                                          \
        mx = MAX(mx, mx2);                                                                         \
        mn = MIN(mn, mn2);                                                                         \
        if (q + nl <= e) {                                                                         \
            vec v = ld(__builtin_assume_aligned(q, VB));                                           \
            mx = MAX(mx, v);                                                                       \
            mn = MIN(mn, v);                                                                       \
            q += nl;                                                                               \
        }                                                                                          \
        if (q < e) {                                                                               \
            vec v = ld(e - nl);                                                                    \
            mx = MAX(mx, v);                                                                       \
            mn = MIN(mn, v);                                                                       \
        }                                                                                          \
        return ANY_GT(mx, SET(h)) | ANY_LT(mn, SET(l));                                            \
    }
DEFINE_OUT(out8, uint8_t, MAX8, MIN8, SET8, ANY_GT8, ANY_LT8)
DEFINE_OUT(out16, uint16_t, MAX16, MIN16, SET16, ANY_GT16, ANY_LT16)

/* The same for a whole block of FT_BLOCK pixels: a fixed number of loads, no branch. */
#define DEFINE_BLOCK_OUT(NAME, T, MAX, MIN, SET, ANY_GT, ANY_LT)                                   \
    static inline int NAME(const T *r, T h, T l) {                                                 \
        const size_t nl = VB / sizeof(T);                                                          \
        vec mx = ld(r), mn = mx;                                                                   \
        for (size_t k = 1; k < FT_BLOCK / nl; k++) {                                               \
            vec v = ld(r + k * nl);                                                                \
            mx = MAX(mx, v);                                                                       \
            mn = MIN(mn, v);                                                                       \
        }                                                                                          \
        return ANY_GT(mx, SET(h)) | ANY_LT(mn, SET(l));                                            \
    }
DEFINE_BLOCK_OUT(block_out8, uint8_t, MAX8, MIN8, SET8, ANY_GT8, ANY_LT8)
DEFINE_BLOCK_OUT(block_out16, uint16_t, MAX16, MIN16, SET16, ANY_GT16, ANY_LT16)

/* The same for the block of FT_BLOCK pixels from x0 of FT_BAND rows at once (r[k]: row k; a band
 * with fewer rows repeats its last one): the band's brightest and darkest pixels there. */
#define DEFINE_BAND_OUT(NAME, T, MAX, MIN, SET, ANY_GT, ANY_LT)                                    \
    static inline int NAME(const T *const *r, size_t x0, T h, T l) {                               \
        const size_t nl = VB / sizeof(T);                                                          \
        vec a = ld(r[0] + x0), b = ld(r[1] + x0), c = ld(r[2] + x0), d = ld(r[3] + x0);            \
        vec mx = MAX(MAX(a, b), MAX(c, d)), mn = MIN(MIN(a, b), MIN(c, d));                        \
        for (size_t j = x0 + nl; j < x0 + FT_BLOCK; j += nl) {                                     \
            a = ld(r[0] + j), b = ld(r[1] + j), c = ld(r[2] + j), d = ld(r[3] + j);                \
            mx = MAX(mx, MAX(MAX(a, b), MAX(c, d)));                                               \
            mn = MIN(mn, MIN(MIN(a, b), MIN(c, d)));                                               \
        }                                                                                          \
        return ANY_GT(mx, SET(h)) | ANY_LT(mn, SET(l));                                            \
    }
DEFINE_BAND_OUT(band_out8, uint8_t, MAX8, MIN8, SET8, ANY_GT8, ANY_LT8)
DEFINE_BAND_OUT(band_out16, uint16_t, MAX16, MIN16, SET16, ANY_GT16, ANY_LT16)

/* Bit x set: pixel x of the block of FT_BLOCK pixels is a candidate (r > hi or r < lo). */
#define DEFINE_MASK_SCALAR(NAME, T)                                                                \
    static inline uint64_t NAME(const T *r, const T *hr, const T *lr, size_t n) {                  \
        uint64_t m = 0;                                                                            \
        for (size_t x = 0; x < n; x++)                                                             \
            m |= (uint64_t)((r[x] > hr[x]) | (r[x] < lr[x])) << x;                                 \
        return m;                                                                                  \
    }
DEFINE_MASK_SCALAR(mask8_scalar, uint8_t)
DEFINE_MASK_SCALAR(mask16_scalar, uint16_t)

#if defined(__AVX512BW__)
static inline uint64_t mask8(const uint8_t *r, const uint8_t *hr, const uint8_t *lr) {
    vec v = ld(r);
    return _mm512_cmpgt_epu8_mask(v, ld(hr)) | _mm512_cmplt_epu8_mask(v, ld(lr));
}
static inline uint64_t mask16(const uint16_t *r, const uint16_t *hr, const uint16_t *lr) {
    uint64_t m = 0;
    for (unsigned k = 0; k < 2; k++) {
        vec v = ld(r + 32 * k);
        uint64_t b = _mm512_cmpgt_epu16_mask(v, ld(hr + 32 * k)) |
                     _mm512_cmplt_epu16_mask(v, ld(lr + 32 * k));
        m |= b << (32 * k);
    }
    return m;
}
#elif defined(__AVX2__)
static inline uint64_t mask8(const uint8_t *r, const uint8_t *hr, const uint8_t *lr) {
    uint64_t m = 0;
    for (unsigned k = 0; k < 2; k++) {
        vec v = ld(r + 32 * k), h = ld(hr + 32 * k), l = ld(lr + 32 * k);
        vec in = _mm256_and_si256(_mm256_cmpeq_epi8(_mm256_max_epu8(v, h), h),
                                  _mm256_cmpeq_epi8(_mm256_min_epu8(v, l), l));
        m |= (uint64_t)(uint32_t)~_mm256_movemask_epi8(in) << (32 * k);
    }
    return m;
}
static inline uint64_t mask16(const uint16_t *r, const uint16_t *hr, const uint16_t *lr) {
    return mask16_scalar(r, hr, lr, FT_BLOCK);
}
#elif defined(__BYTE_ORDER__) && __BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__
/* Lane compares give all-ones lanes; within each 64-bit word, keeping bit i of lane i and summing
 * the lanes with one multiply packs them into a few mask bits (the lanes' bits never overlap). */
static inline uint64_t pack_bits(vec c, unsigned lane_bytes) {
    const uint64_t keep = lane_bytes == 1 ? 0x8040201008040201ull : 0x0008000400020001ull;
    const uint64_t sum = lane_bytes == 1 ? 0x0101010101010101ull : 0x0001000100010001ull;
    const unsigned per = 8 / lane_bytes, top = 64 - 8 * lane_bytes;
    vec64 w = (vec64)c;
    uint64_t m = 0;
    for (unsigned i = 0; i < VB / 8; i++)
        m |= (((w[i] & keep) * sum) >> top) << (per * i);
    return m;
}
static inline uint64_t mask8(const uint8_t *r, const uint8_t *hr, const uint8_t *lr) {
    uint64_t m = 0;
    for (unsigned k = 0; k < FT_BLOCK / VB; k++) {
        vec v = ld(r + VB * k);
        vec c = (vec)(v > ld(hr + VB * k)) | (vec)(v < ld(lr + VB * k));
        m |= pack_bits(c, 1) << (VB * k);
    }
    return m;
}
static inline uint64_t mask16(const uint16_t *r, const uint16_t *hr, const uint16_t *lr) {
    const unsigned nl = VB / 2;
    uint64_t m = 0;
    for (unsigned k = 0; k < FT_BLOCK / nl; k++) {
        vec16 v = (vec16)ld(r + nl * k);
        vec c = (vec)((v > (vec16)ld(hr + nl * k)) | (v < (vec16)ld(lr + nl * k)));
        m |= pack_bits(c, 2) << (nl * k);
    }
    return m;
}
#else
static inline uint64_t mask8(const uint8_t *r, const uint8_t *hr, const uint8_t *lr) {
    return mask8_scalar(r, hr, lr, FT_BLOCK);
}
static inline uint64_t mask16(const uint16_t *r, const uint16_t *hr, const uint16_t *lr) {
    return mask16_scalar(r, hr, lr, FT_BLOCK);
}
#endif

/* ---------------------------------------------------------------------------------------------- */
/* Runs from the masks */

typedef struct {
    ft_fx *fx;
    uint32_t n, nr; /* candidates, runs */
    int overflow;
} scan_state;

/* Candidates xs .. xe - 1 of row y (r: the row, m: its background means). A run that ends where
 * the last one of this row ended (at a block edge) goes on. Returns 0 when the candidate cap is
 * reached (the candidates up to it are kept, as a per-pixel scan would keep them). */
#define DEFINE_ADD_RUN(NAME, T)                                                                    \
    static inline int NAME(scan_state *s, const T *r, const float *m, uint32_t y, uint32_t xs,     \
                           uint32_t xe) {                                                          \
        ft_fx *fx = s->fx;                                                                         \
        int full = 0;                                                                              \
        if (xe - xs > fx->cap - s->n) {                                                            \
            xe = xs + (fx->cap - s->n);                                                            \
            full = 1;                                                                              \
            s->overflow = 1;                                                                       \
            if (xe == xs)                                                                          \
                return 0;                                                                          \
        }                                                                                          \
        ft_run *last = s->nr ? &fx->runs[s->nr - 1] : NULL;                                        \
        if (last && last->y == y && last->x1 == xs) {                                              \
            last->x1 = xe;                                                                         \
        } else {                                                                                   \
            ft_run *q = &fx->runs[s->nr++];                                                        \
            q->y = y;                                                                              \
            q->x0 = xs;                                                                            \
            q->x1 = xe;                                                                            \
            q->c0 = s->n;                                                                          \
        }                                                                                          \
        float *d = fx->cand_d + s->n;                                                              \
        const uint32_t len = xe - xs;                                                              \
        if (fx->p.polarity == FT_FX_POLARITY_BOTH)                                                 \
            for (uint32_t k = 0; k < len; k++)                                                     \
                d[k] = fabsf((float)r[xs + k] - m[xs + k]);                                        \
        else if (fx->p.polarity == FT_FX_POLARITY_DARK)                                            \
            for (uint32_t k = 0; k < len; k++)                                                     \
                d[k] = -((float)r[xs + k] - m[xs + k]);                                            \
        else                                                                                       \
            for (uint32_t k = 0; k < len; k++)                                                     \
                d[k] = (float)r[xs + k] - m[xs + k];                                               \
        s->n += len;                                                                               \
        return !full;                                                                              \
    }                                                                                              \
    /* Every run of set bits of mask (bit i: pixel x0 + i). */                                     \
    static inline int NAME##_mask(scan_state *s, const T *r, const float *m, uint32_t y,           \
                                  uint32_t x0, uint64_t mask) {                                    \
        while (mask) {                                                                             \
            unsigned a = (unsigned)__builtin_ctzll(mask);                                          \
            uint64_t rest = ~(mask >> a); /* zero bits: the run */                                 \
            unsigned len = rest ? (unsigned)__builtin_ctzll(rest) : 64u - a;                       \
            if (!NAME(s, r, m, y, x0 + a, x0 + a + len))                                           \
                return 0;                                                                          \
            mask = a + len >= 64 ? 0 : mask & (~0ull << (a + len));                                \
        }                                                                                          \
        return 1;                                                                                  \
    }
DEFINE_ADD_RUN(add_run8, uint8_t)
DEFINE_ADD_RUN(add_run16, uint16_t)

/* ---------------------------------------------------------------------------------------------- */
/* The scan */

/* The thresholds of a queued block and the background means of its candidates are read only
 * where there are candidates, so they may well be in memory: they are fetched ahead of their use.
 */
static inline void prefetch_thresholds(const void *hr, const void *lr, size_t bytes) {
    const char *h = hr, *l = lr;
    for (size_t o = 0; o < bytes; o += 64) {
        __builtin_prefetch(h + o);
        __builtin_prefetch(l + o);
    }
    __builtin_prefetch(h + bytes - 1);
    __builtin_prefetch(l + bytes - 1);
}

/* The background means of the candidates in mask (16 pixels of floats: one or two cache lines). */
static inline void prefetch_means(const float *m, uint64_t mask) {
    for (unsigned g = 0; g < 4; g++)
        if ((mask >> (16 * g)) & 0xffffu) {
            __builtin_prefetch(m + 16 * g);
            __builtin_prefetch(m + 16 * g + 15);
        }
}

/* Two passes. The first reads the frame alone: bands, their blocks, and the failing blocks row by
 * row against their bounds; a block that fails is queued (in raster order) and its thresholds are
 * prefetched. The second computes the queued blocks' candidate masks (their thresholds have come in
 * meanwhile, the misses overlapping), prefetches the background means of their candidates, then
 * keeps the candidates with their differences, in raster order. (plain: every pixel of every row
 * against its thresholds.) */
#define DEFINE_SCAN(NAME, T, HI, LO, BHI, BLO, GHI, GLO, WHI, WLO, OUT, MASK, ADD)                 \
    uint32_t NAME(ft_fx *fx, const T *img, size_t stride_px, uint32_t *n_cand, int *overflow) {    \
        const size_t w = fx->w, nblk = fx->nblk, nfull = w / FT_BLOCK;                             \
        scan_state s = {fx, 0, 0, 0};                                                              \
        if (fx->scalar_scan) {                                                                     \
            for (uint32_t y = 0; y < fx->h; y++) {                                                 \
                const T *r = img + y * stride_px, *hr = fx->HI + y * w, *lr = fx->LO + y * w;      \
                for (size_t x0 = 0; x0 < w; x0 += FT_BLOCK) {                                      \
                    const size_t n = w - x0 < FT_BLOCK ? w - x0 : FT_BLOCK;                        \
                    uint64_t mk = MASK##_scalar(r + x0, hr + x0, lr + x0, n);                      \
                    if (mk && !ADD##_mask(&s, r, fx->mean + y * w, y, (uint32_t)x0, mk))           \
                        goto done;                                                                 \
                }                                                                                  \
            }                                                                                      \
            goto done;                                                                             \
        }                                                                                          \
        uint32_t nq = 0;                                                                           \
        const size_t nw = (nblk + 63) / 64;                                                        \
        for (uint32_t y0 = 0; y0 < fx->h; y0 += FT_BAND) {                                         \
            const uint32_t nb = fx->h - y0 < FT_BAND ? fx->h - y0 : FT_BAND;                       \
            const T *r[FT_BAND];                                                                   \
            for (uint32_t k = 0; k < FT_BAND; k++)                                                 \
                r[k] = img + (size_t)(y0 + (k < nb ? k : nb - 1)) * stride_px;                     \
            { /* the band against its loosest bounds: the common case, nothing there */            \
                const T wh = fx->WHI[y0 / FT_BAND], wl = fx->WLO[y0 / FT_BAND];                    \
                int f = 0;                                                                         \
                if (stride_px == w) /* packed rows: one range */                                   \
                    f = OUT(r[0], w * nb, wh, wl);                                                 \
                else                                                                               \
                    for (uint32_t k = 0; k < nb; k++)                                              \
                        f |= OUT(r[k], w, wh, wl);                                                 \
                if (!f)                                                                            \
                    continue;                                                                      \
            }                                                                                      \
            const T *gh = fx->GHI + y0 / FT_BAND * nblk, *gl = fx->GLO + y0 / FT_BAND * nblk;      \
            uint64_t fails[4] = {0, 0, 0, 0}, any = 0;  /* nblk <= 256 */                          \
            for (size_t b0 = 0; b0 < nfull; b0 += 64) { /* no branch: a bit per block */           \
                const size_t b1 = nfull - b0 < 64 ? nfull : b0 + 64;                               \
                uint64_t fw = 0;                                                                   \
                for (size_t b = b0; b < b1; b++)                                                   \
                    fw |= (uint64_t)band_##OUT(r, b * FT_BLOCK, gh[b], gl[b]) << (b - b0);         \
                fails[b0 / 64] = fw;                                                               \
            }                                                                                      \
            if (nfull < nblk) { /* a short last block */                                           \
                int f = 0;                                                                         \
                for (uint32_t k = 0; k < nb; k++)                                                  \
                    f |= OUT(r[k] + nfull * FT_BLOCK, w - nfull * FT_BLOCK, gh[nfull], gl[nfull]); \
                fails[nfull / 64] |= (uint64_t)f << (nfull % 64);                                  \
            }                                                                                      \
            for (size_t i = 0; i < nw; i++)                                                        \
                any |= fails[i];                                                                   \
            if (!any) /* every block of the band passes: no candidate */                           \
                continue;                                                                          \
            for (uint32_t k = 0; k < nb; k++) { /* the failing blocks row by row: raster order */  \
                const uint32_t y = y0 + k;                                                         \
                if (fx->pending[y]) /* its bounds hold whatever the update: make them exact */     \
                    ft_fx_bg_row(fx, y);                                                           \
                const T *bh = fx->BHI + y * nblk, *bl = fx->BLO + y * nblk;                        \
                for (size_t i = 0; i < nw; i++)                                                    \
                    for (uint64_t fw = fails[i]; fw; fw &= fw - 1) {                               \
                        const size_t b = 64 * i + (size_t)__builtin_ctzll(fw), x0 = b * FT_BLOCK;  \
                        const size_t n = w - x0 < FT_BLOCK ? w - x0 : FT_BLOCK;                    \
                        int f = n == FT_BLOCK ? block_##OUT(r[k] + x0, bh[b], bl[b])               \
                                              : OUT(r[k] + x0, n, bh[b], bl[b]);                   \
                        if (!f)                                                                    \
                            continue;                                                              \
                        prefetch_thresholds(fx->HI + y * w + x0, fx->LO + y * w + x0,              \
                                            n * sizeof(T));                                        \
                        fx->queue[nq++] = y << 8 | (uint32_t)b;                                    \
                    }                                                                              \
            }                                                                                      \
        }                                                                                          \
        for (uint32_t k = 0; k < nq; k++) { /* the masks; the means of their candidates fetched */ \
            const uint32_t y = fx->queue[k] >> 8;                                                  \
            const size_t x0 = (fx->queue[k] & 0xffu) * FT_BLOCK, i = y * w + x0;                   \
            const size_t n = w - x0 < FT_BLOCK ? w - x0 : FT_BLOCK;                                \
            const T *r = img + y * stride_px;                                                      \
            fx->qmask[k] = n == FT_BLOCK ? MASK(r + x0, fx->HI + i, fx->LO + i)                    \
                                         : MASK##_scalar(r + x0, fx->HI + i, fx->LO + i, n);       \
            prefetch_means(fx->mean + i, fx->qmask[k]);                                            \
        }                                                                                          \
        for (uint32_t k = 0; k < nq; k++) { /* then the candidates, in raster order */             \
            const uint32_t y = fx->queue[k] >> 8, x0 = (fx->queue[k] & 0xffu) * FT_BLOCK;          \
            if (fx->qmask[k] &&                                                                    \
                !ADD##_mask(&s, img + y * stride_px, fx->mean + y * w, y, x0, fx->qmask[k]))       \
                goto done;                                                                         \
        }                                                                                          \
    done:                                                                                          \
        *n_cand = s.n;                                                                             \
        *overflow = s.overflow;                                                                    \
        return s.nr;                                                                               \
    }
DEFINE_SCAN(FT_NAME(ft_fx_scan8), uint8_t, hi8, lo8, bhi8, blo8, ghi8, glo8, whi8, wlo8, out8,
            mask8, add_run8)
DEFINE_SCAN(FT_NAME(ft_fx_scan16), uint16_t, hi16, lo16, bhi16, blo16, ghi16, glo16, whi16, wlo16,
            out16, mask16, add_run16)

const ft_fx_scan_impl FT_NAME(ft_fx_scan) = {FT_STR(FT_PATH), FT_NAME(ft_fx_scan8),
                                             FT_NAME(ft_fx_scan16)};

#ifndef FT_SCAN_VARIANT /* the baseline compile: the choice of path, and the test hooks */

/* FT_FX_DISPATCH (the portable x86 build): the wider paths are linked in, compiled apart for the
 * x86-64 levels v4 and v3, and entered only on a CPU of that level (libgcc's checks include the OS
 * saving the wide registers). */
#ifdef FT_FX_DISPATCH
static int cpu_runs(const ft_fx_scan_impl *s) {
    __builtin_cpu_init(); /* needed only before constructors have run; cheap after */
    if (s == &ft_fx_scan_avx512bw)
        return __builtin_cpu_supports("x86-64-v4");
    if (s == &ft_fx_scan_avx2)
        return __builtin_cpu_supports("x86-64-v3");
    return 1;
}
static const ft_fx_scan_impl *const paths[] = {&ft_fx_scan_avx512bw, &ft_fx_scan_avx2,
                                               &FT_NAME(ft_fx_scan)};
#else
static int cpu_runs(const ft_fx_scan_impl *s) {
    (void)s;
    return 1; /* the only path is the one this file was compiled for */
}
static const ft_fx_scan_impl *const paths[] = {&FT_NAME(ft_fx_scan)};
#endif

/* The widest first. */
const ft_fx_scan_impl *ft_fx_scan_select(void) {
    for (size_t i = 0; i < sizeof paths / sizeof paths[0]; i++)
        if (cpu_runs(paths[i]))
            return paths[i];
    return paths[sizeof paths / sizeof paths[0] - 1];
}

int ft_fx_debug_scan_force(ft_fx *fx, const char *name) {
    for (size_t i = 0; fx && name && i < sizeof paths / sizeof paths[0]; i++)
        if (!strcmp(paths[i]->name, name) && cpu_runs(paths[i])) {
            fx->scan = paths[i];
            return 0;
        }
    return -1;
}

const char *ft_fx_debug_scan_path(const ft_fx *fx) {
    return fx && fx->scan ? fx->scan->name : "none";
}

void ft_fx_debug_scalar_scan(ft_fx *fx, int on) {
    if (fx)
        fx->scalar_scan = on != 0;
}
#endif
