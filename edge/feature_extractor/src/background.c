/* The background model of libflytrack_features: the running average (mean, mean of squares), the
 * per-pixel thresholds and the bounds of blocks and bands of them that the scan (scan.c) reads, and
 * the update of all of it every bg_update_interval frames, spread over the frames that follow. */
#include "fx_internal.h"
#include "thresholds.h"

#include <string.h>

/* Per-pixel thresholds from the background. A pixel value x is a candidate when
 *   x > mean + T   <=>  x > floor(mean + T)      (x integer)  -> hi = floor(mean + T)
 *   x < mean - T   <=>  x < ceil(mean - T)                    -> lo = ceil(mean - T)
 * with T = max(diff_threshold, n_sigma * std). hi = maxval means "never brighter", lo = 0 "never
 * darker". Nonnegative float -> int conversion truncates, which is floor; it vectorises. */

thr_cfg ft_fx_thr_config(const ft_fx *fx) {
    thr_cfg c;
    c.a = (float)fx->p.alpha;
    c.a1 = (float)(1.0 - fx->p.alpha);
    c.ns = (float)fx->p.n_sigma;
    c.dt = (float)fx->p.diff_threshold;
    c.maxv = (float)fx->maxval;
    c.bright = fx->p.polarity != FT_FX_POLARITY_DARK;
    c.dark = fx->p.polarity != FT_FX_POLARITY_BRIGHT;
    return c;
}

/* Running average: mean <- (1 - a) mean + a x, sumsq <- (1 - a) sumsq + a x^2; init: mean = x. */
#define DEFINE_UPDATE(NAME, T)                                                                     \
    static FT_FX_CLONES void NAME(size_t w, size_t h, const T *restrict img, size_t stride_px,     \
                                  float *restrict mean, float *restrict sumsq, int init,           \
                                  thr_cfg c) {                                                     \
        for (size_t y = 0; y < h; y++) {                                                           \
            const T *restrict r = img + y * stride_px;                                             \
            float *restrict m = mean + y * w;                                                      \
            float *restrict s = sumsq + y * w;                                                     \
            if (init) {                                                                            \
                for (size_t x = 0; x < w; x++) {                                                   \
                    float v = (float)r[x];                                                         \
                    m[x] = v;                                                                      \
                    s[x] = v * v;                                                                  \
                }                                                                                  \
            } else {                                                                               \
                for (size_t x = 0; x < w; x++) {                                                   \
                    float v = (float)r[x];                                                         \
                    m[x] = c.a1 * m[x] + c.a * v;                                                  \
                    s[x] = c.a1 * s[x] + c.a * (v * v);                                            \
                }                                                                                  \
            }                                                                                      \
        }                                                                                          \
    }
DEFINE_UPDATE(update8, uint8_t)
DEFINE_UPDATE(update16, uint16_t)

/* bhi = min(hi), blo = max(lo) over each block of FT_BLOCK pixels of a row (the last one may be
 * short). */
#define DEFINE_BLOCK_BOUNDS(NAME, T)                                                               \
    static FT_FX_CLONES void NAME(size_t w, size_t h, size_t nblk, const T *restrict hi,           \
                                  const T *restrict lo, T *restrict bhi, T *restrict blo) {        \
        for (size_t y = 0; y < h; y++) {                                                           \
            for (size_t b = 0; b < nblk; b++) {                                                    \
                size_t x0 = b * FT_BLOCK, x1 = x0 + FT_BLOCK < w ? x0 + FT_BLOCK : w;              \
                T mh = hi[y * w + x0], ml = lo[y * w + x0];                                        \
                for (size_t x = x0; x < x1; x++) { /* from x0: whole vectors, no scalar tail */    \
                    T vh = hi[y * w + x], vl = lo[y * w + x];                                      \
                    mh = vh < mh ? vh : mh;                                                        \
                    ml = vl > ml ? vl : ml;                                                        \
                }                                                                                  \
                bhi[y * nblk + b] = mh;                                                            \
                blo[y * nblk + b] = ml;                                                            \
            }                                                                                      \
        }                                                                                          \
    }
DEFINE_BLOCK_BOUNDS(block_bounds8, uint8_t)
DEFINE_BLOCK_BOUNDS(block_bounds16, uint16_t)

/* ghi = min(bhi), glo = max(blo) over the rows of each band of FT_BAND rows (the last one may have
 * fewer), block by block; whi, wlo the same over the whole band. */
#define DEFINE_BAND_BOUNDS(NAME, T)                                                                \
    static FT_FX_CLONES void NAME(size_t h, size_t nblk, const T *restrict bhi,                    \
                                  const T *restrict blo, T *restrict ghi, T *restrict glo,         \
                                  T *restrict whi, T *restrict wlo) {                              \
        for (size_t y0 = 0; y0 < h; y0 += FT_BAND) {                                               \
            T *restrict gh = ghi + y0 / FT_BAND * nblk, *restrict gl = glo + y0 / FT_BAND * nblk;  \
            memcpy(gh, bhi + y0 * nblk, nblk * sizeof(T));                                         \
            memcpy(gl, blo + y0 * nblk, nblk * sizeof(T));                                         \
            for (size_t y = y0 + 1; y < h && y < y0 + FT_BAND; y++)                                \
                for (size_t b = 0; b < nblk; b++) {                                                \
                    T vh = bhi[y * nblk + b], vl = blo[y * nblk + b];                              \
                    gh[b] = vh < gh[b] ? vh : gh[b];                                               \
                    gl[b] = vl > gl[b] ? vl : gl[b];                                               \
                }                                                                                  \
            T mh = gh[0], ml = gl[0];                                                              \
            for (size_t b = 1; b < nblk; b++) {                                                    \
                mh = gh[b] < mh ? gh[b] : mh;                                                      \
                ml = gl[b] > ml ? gl[b] : ml;                                                      \
            }                                                                                      \
            whi[y0 / FT_BAND] = mh;                                                                \
            wlo[y0 / FT_BAND] = ml;                                                                \
        }                                                                                          \
    }
DEFINE_BAND_BOUNDS(band_bounds8, uint8_t)
DEFINE_BAND_BOUNDS(band_bounds16, uint16_t)

/* Thresholds and block bounds of rows y0 .. y1 - 1 (the band bounds once all rows are done), and
 * the bounds these rows' blocks will keep after the next update whatever its frame (see below). */
static void refresh_rows(ft_fx *fx, thr_cfg c, size_t y0, size_t y1) {
    const size_t o = y0 * fx->w, n = (y1 - y0) * fx->w, ob = y0 * fx->nblk;
    const uint8_t *um = fx->has_mask ? fx->mask + o : NULL;
    if (fx->hi16) {
        ft_fx_thresh16(n, fx->mean + o, fx->sumsq + o, um, fx->hi16 + o, fx->lo16 + o, c);
        block_bounds16(fx->w, y1 - y0, fx->nblk, fx->hi16 + o, fx->lo16 + o, fx->bhi16 + ob,
                       fx->blo16 + ob);
        for (size_t y = y0; y < y1; y++)
            ft_fx_next_bounds16(fx->w, FT_BLOCK, fx->mean + y * fx->w, fx->nbhi16 + y * fx->nblk,
                                fx->nblo16 + y * fx->nblk, c);
    } else {
        ft_fx_thresh8(n, fx->mean + o, fx->sumsq + o, um, fx->hi8 + o, fx->lo8 + o, c);
        block_bounds8(fx->w, y1 - y0, fx->nblk, fx->hi8 + o, fx->lo8 + o, fx->bhi8 + ob,
                      fx->blo8 + ob);
        for (size_t y = y0; y < y1; y++)
            ft_fx_next_bounds8(fx->w, FT_BLOCK, fx->mean + y * fx->w, fx->nbhi8 + y * fx->nblk,
                               fx->nblo8 + y * fx->nblk, c);
    }
}

/* The band bounds of bands g0 .. g1 - 1 from their rows' block bounds. */
static void refresh_band_bounds(ft_fx *fx, size_t g0, size_t g1) {
    const size_t y0 = g0 * FT_BAND, y1 = g1 * FT_BAND < fx->h ? g1 * FT_BAND : fx->h;
    const size_t ob = y0 * fx->nblk, og = g0 * fx->nblk;
    if (fx->hi16)
        band_bounds16(y1 - y0, fx->nblk, fx->bhi16 + ob, fx->blo16 + ob, fx->ghi16 + og,
                      fx->glo16 + og, fx->whi16 + g0, fx->wlo16 + g0);
    else
        band_bounds8(y1 - y0, fx->nblk, fx->bhi8 + ob, fx->blo8 + ob, fx->ghi8 + og, fx->glo8 + og,
                     fx->whi8 + g0, fx->wlo8 + g0);
}

static size_t n_bands(const ft_fx *fx) {
    return (fx->h + FT_BAND - 1) / FT_BAND;
}

/* Rows per band of the background update: about 2048 pixels, whose 16 kB of floats stay in the L1
 * cache from the running average to the thresholds and bounds (one pass over memory, not three). */
static size_t band_rows(const ft_fx *fx) {
    return fx->w >= 2048 ? 1 : 2048 / fx->w;
}

/* Running average of rows y0 .. y1 - 1 with the frame img (rows stride_bytes apart), then their
 * thresholds and bounds. */
static void update_rows(ft_fx *fx, thr_cfg c, const void *img, size_t stride_bytes, size_t y0,
                        size_t y1, int init) {
    const size_t o = y0 * fx->w;
    const uint8_t *band = (const uint8_t *)img + y0 * stride_bytes;
    if (fx->p.pixel_format == FT_FX_MONO16)
        update16(fx->w, y1 - y0, (const uint16_t *)band, stride_bytes / 2, fx->mean + o,
                 fx->sumsq + o, init, c);
    else
        update8(fx->w, y1 - y0, band, stride_bytes, fx->mean + o, fx->sumsq + o, init, c);
    refresh_rows(fx, c, y0, y1);
}

/* The whole model at once: every band of rows while it is in the L1 cache. */
static void update_all(ft_fx *fx, const void *img, size_t stride_bytes, int init) {
    thr_cfg c = ft_fx_thr_config(fx);
    for (size_t y0 = 0, nb = band_rows(fx); y0 < fx->h; y0 += nb)
        update_rows(fx, c, img, stride_bytes, y0, y0 + nb < fx->h ? y0 + nb : fx->h, init);
    refresh_band_bounds(fx, 0, n_bands(fx));
}

/* ---------------------------------------------------------------------------------------------- */
/* The update spread over the frames that follow it
 *
 * Updating the whole model in the frame that asks for it reads and writes all of it at once (32 MB
 * at 2048 x 2048): a frame of milliseconds every bg_update_interval frames. Instead, that frame's
 * pixels are copied aside and each row of the model is brought up to date later, from that copy:
 * a few rows after each following frame (about h / (interval - 1) of them), and any row at once
 * when the scan needs its thresholds. Until then a row's block bounds are bounds that hold after
 * the update whatever the frame held (computed with its last thresholds, see ft_fx_next_bounds8):
 * a block within them holds no candidate under the updated model either, and a block outside them
 * makes the scan bring its row up to date before it tests the block against the row's own bounds.
 * The rows are independent, so the model, the thresholds and every result are the same, bit for
 * bit, as with the whole update done at once (tests/test_lazy_update.c checks it). */

void ft_fx_bg_row(ft_fx *fx, uint32_t y) {
    if (!fx->pending[y])
        return;
    const size_t bpp = fx->p.pixel_format == FT_FX_MONO16 ? 2 : 1, sb = fx->w * bpp;
    update_rows(fx, fx->lazy_cfg, fx->saved, sb, y, y + 1, 0);
    fx->pending[y] = 0;
    fx->n_pending--;
    refresh_band_bounds(fx, y / FT_BAND, y / FT_BAND + 1);
}

/* Brings up to date the pending rows among y0 .. y1 - 1, runs of consecutive ones a band of rows
 * (band_rows) at a time as the whole update does (one row at a time costs about 15% more), then
 * the bounds of their bands. */
static void bring_rows(ft_fx *fx, uint32_t y0, uint32_t y1) {
    const size_t bpp = fx->p.pixel_format == FT_FX_MONO16 ? 2 : 1, sb = fx->w * bpp;
    const uint32_t nb = (uint32_t)band_rows(fx);
    for (uint32_t y = y0; y < y1;) {
        if (!fx->pending[y]) {
            y++;
            continue;
        }
        uint32_t e = y + 1;
        while (e < y1 && e < y + nb && fx->pending[e])
            e++;
        update_rows(fx, fx->lazy_cfg, fx->saved, sb, y, e, 0);
        memset(fx->pending + y, 0, e - y);
        fx->n_pending -= e - y;
        y = e;
    }
    if (y0 < y1)
        refresh_band_bounds(fx, y0 / FT_BAND, (y1 - 1) / FT_BAND + 1);
}

void ft_fx_bg_finish(ft_fx *fx) {
    if (fx->n_pending)
        bring_rows(fx, 0, fx->h);
}

void ft_fx_bg_step(ft_fx *fx) {
    if (!fx->n_pending)
        return;
    const uint32_t iv = fx->p.bg_update_interval, spread = iv > 2 ? iv - 1 : 1;
    const uint32_t k = (fx->h + spread - 1) / spread, y0 = fx->lazy_next;
    const uint32_t y1 = fx->h - y0 < k ? fx->h : y0 + k;
    bring_rows(fx, y0, y1); /* rows the scan brought up to date already are skipped */
    fx->lazy_next = y1;
}

/* Swaps two arrays of block bounds (the current ones and those after the next update). */
#define SWAP_PTR(a, b)                                                                             \
    do {                                                                                           \
        void *t_ = (void *)(a);                                                                    \
        (a) = (b);                                                                                 \
        (b) = t_;                                                                                  \
    } while (0)

void ft_fx_bg_take(ft_fx *fx, const void *img, size_t stride_bytes) {
    memset(fx->pending, 0, fx->h);
    fx->n_pending = 0;
    update_all(fx, img, stride_bytes, 1);
    fx->have_bg = 1;
}

void ft_fx_bg_update(ft_fx *fx, const void *img, size_t stride_bytes) {
    ft_fx_bg_finish(fx);
    if (fx->eager_update) {
        update_all(fx, img, stride_bytes, 0);
        return;
    }
    const size_t bpp = fx->p.pixel_format == FT_FX_MONO16 ? 2 : 1, sb = fx->w * bpp;
    for (size_t y = 0; y < fx->h; y++)
        memcpy((uint8_t *)fx->saved + y * sb, (const uint8_t *)img + y * stride_bytes, sb);
    if (fx->hi16) {
        SWAP_PTR(fx->bhi16, fx->nbhi16);
        SWAP_PTR(fx->blo16, fx->nblo16);
    } else {
        SWAP_PTR(fx->bhi8, fx->nbhi8);
        SWAP_PTR(fx->blo8, fx->nblo8);
    }
    refresh_band_bounds(fx, 0, n_bands(fx));
    memset(fx->pending, 1, fx->h);
    fx->n_pending = fx->h;
    fx->lazy_next = 0;
    fx->lazy_cfg = ft_fx_thr_config(fx);
}

void ft_fx_bg_refresh(ft_fx *fx) {
    ft_fx_bg_finish(fx);
    thr_cfg c = ft_fx_thr_config(fx);
    for (size_t y0 = 0, nb = band_rows(fx); y0 < fx->h; y0 += nb)
        refresh_rows(fx, c, y0, y0 + nb < fx->h ? y0 + nb : fx->h);
    refresh_band_bounds(fx, 0, n_bands(fx));
}

void ft_fx_debug_eager_update(ft_fx *fx, int on) {
    if (fx)
        fx->eager_update = on != 0;
}

uint32_t ft_fx_debug_pending_rows(const ft_fx *fx) {
    return fx ? fx->n_pending : 0;
}
