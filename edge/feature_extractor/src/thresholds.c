/* Per-pixel candidate thresholds, in a file of its own because it is compiled with
 * -ffinite-math-only -fno-signed-zeros: without them GCC will not turn the float clamps into vector
 * max/min, and this loop runs over every pixel at each background update. Every input here is
 * finite (pixel values and checked parameters) and the sign of a zero never changes a threshold, so
 * the flags change no result; they are kept out of features.c, whose isfinite() checks must stay.
 */
#include "thresholds.h"

#include <math.h>

/* Branch-free on purpose: a conditional here lets the compiler skip the float loads for masked
 * pixels, and then it no longer vectorises the loop. USE(i): whether pixel i is used. */
#define DEFINE_THRESH_LOOP(NAME, T, USE)                                                           \
    static FT_FX_CLONES void NAME(size_t n, const float *restrict mean,                            \
                                  const float *restrict sumsq, const uint8_t *restrict mask,       \
                                  T *restrict hi, T *restrict lo, thr_cfg c) {                     \
        const uint32_t bright = c.bright ? 1u : 0u, dark = c.dark ? 1u : 0u;                       \
        const uint32_t maxv = (uint32_t)c.maxv;                                                    \
        (void)mask;                                                                                \
        for (size_t i = 0; i < n; i++) {                                                           \
            float m = mean[i];                                                                     \
            float var = sumsq[i] - m * m;                                                          \
            var = var > 0.0f ? var : 0.0f;                                                         \
            float t = c.ns * sqrtf(var);                                                           \
            t = t > c.dt ? t : c.dt;                                                               \
            float up = m + t;                                                                      \
            float dn = m - t;                                                                      \
            up = up < c.maxv ? up : c.maxv;                                                        \
            dn = dn > 0.0f ? dn : 0.0f;                                                            \
            uint32_t h = (uint32_t)(int32_t)up;                                                    \
            int32_t di = (int32_t)dn;                                                              \
            uint32_t l = (uint32_t)(di + ((float)di < dn));                                        \
            uint32_t use = USE(i);                                                                 \
            uint32_t mb = 0u - (use & bright), md = 0u - (use & dark);                             \
            hi[i] = (T)((h & mb) | (maxv & ~mb));                                                  \
            lo[i] = (T)(l & md);                                                                   \
        }                                                                                          \
    }

#define MASKED(i) (mask[i] != 0)
#define ALL(i) 1u
DEFINE_THRESH_LOOP(thresh8_masked, uint8_t, MASKED)
DEFINE_THRESH_LOOP(thresh16_masked, uint16_t, MASKED)
DEFINE_THRESH_LOOP(thresh8_all, uint8_t, ALL)
DEFINE_THRESH_LOOP(thresh16_all, uint16_t, ALL)

/* Without a mask (NULL) every pixel is used and the mask is not read: one byte per pixel less to
 * bring in at each update. */
void ft_fx_thresh8(size_t n, const float *restrict mean, const float *restrict sumsq,
                   const uint8_t *restrict mask, uint8_t *restrict hi, uint8_t *restrict lo,
                   thr_cfg c) {
    if (mask)
        thresh8_masked(n, mean, sumsq, mask, hi, lo, c);
    else
        thresh8_all(n, mean, sumsq, mask, hi, lo, c);
}
void ft_fx_thresh16(size_t n, const float *restrict mean, const float *restrict sumsq,
                    const uint8_t *restrict mask, uint16_t *restrict hi, uint16_t *restrict lo,
                    thr_cfg c) {
    if (mask)
        thresh16_masked(n, mean, sumsq, mask, hi, lo, c);
    else
        thresh16_all(n, mean, sumsq, mask, hi, lo, c);
}

/* Bounds that a block's thresholds keep after the next background update, whatever that frame
 * holds (pixel values v in [0, maxv]), from the block's background means now (lowest mn, highest
 * mx). With m' = a1 m + a v and T' = max(dt, n_sigma std') >= dt:
 *   hi' = floor(min(m' + T', maxv)) >= floor(min(a1 m + dt, maxv))
 *   lo' = ceil(max(m' - T', 0))     <= ceil(max(a1 m + a maxv - dt, 0))
 * Each float operation above rounds by at most one part in 2^24, and pixels that are masked or of
 * the ignored polarity have hi = maxv and lo = 0; the bounds here are loosened by more than the
 * rounding and by one more level. */
#define DEFINE_NEXT_BOUNDS(NAME, T)                                                                \
    FT_FX_CLONES void NAME(size_t w, size_t blk, const float *restrict mean, T *restrict nbhi,     \
                           T *restrict nblo, thr_cfg c) {                                          \
        float mnv[64], mxv[64];                                                                    \
        for (size_t c0 = 0; c0 < w; c0 += 64 * blk, nbhi += 64, nblo += 64) {                      \
            size_t nb = 0; /* up to 64 blocks: their ranges of means, then their bounds */         \
            for (size_t x0 = c0; x0 < w && nb < 64; x0 += blk, nb++) {                             \
                const size_t x1 = x0 + blk < w ? x0 + blk : w;                                     \
                float mn = mean[x0], mx = mean[x0];                                                \
                for (size_t x = x0; x < x1; x++) {                                                 \
                    mn = mean[x] < mn ? mean[x] : mn;                                              \
                    mx = mean[x] > mx ? mean[x] : mx;                                              \
                }                                                                                  \
                mnv[nb] = mn;                                                                      \
                mxv[nb] = mx;                                                                      \
            }                                                                                      \
            for (size_t b = 0; b < nb; b++) { /* apart: this loop vectorises over the blocks */    \
                double up = ((double)c.a1 * mnv[b] * (1.0 - 1e-6) + c.dt) * (1.0 - 1e-6) - 1.0;    \
                up = up < c.maxv ? up : c.maxv;                                                    \
                up = up > 0.0 ? floor(up) : 0.0;                                                   \
                nbhi[b] = (T)(int32_t)up;                                                          \
                double dn = ((double)c.a1 * mxv[b] + (double)c.a * c.maxv) * (1.0 + 1e-6) - c.dt;  \
                dn = dn > 0.0 ? ceil(dn * (1.0 + 1e-6)) + 1.0 : 0.0;                               \
                dn = dn < c.maxv ? dn : c.maxv;                                                    \
                nblo[b] = (T)(int32_t)dn;                                                          \
            }                                                                                      \
        }                                                                                          \
    }

DEFINE_NEXT_BOUNDS(ft_fx_next_bounds8, uint8_t)
DEFINE_NEXT_BOUNDS(ft_fx_next_bounds16, uint16_t)
