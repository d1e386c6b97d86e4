/* Internal: per-pixel candidate thresholds from the background model (see features.c). */
#ifndef FLYTRACK_FX_THRESHOLDS_H
#define FLYTRACK_FX_THRESHOLDS_H

#include <stddef.h>
#include <stdint.h>

/* The portable x86 build (FT_FX_DISPATCH) compiles the per-pixel loops of the background model once
 * per x86-64 level, v4 (AVX-512) and v3 (AVX2), as the scan's wider paths are (scan.c), and GCC
 * runs the widest this CPU has (an ifunc, resolved at load): they run over every pixel at each
 * update. Each clone gives the same floats: every operation rounds as IEEE says
 * whatever the width, and -ffp-contract=off keeps fused multiply-adds out. */
#if defined(FT_FX_DISPATCH) && defined(__x86_64__)
#define FT_FX_CLONES __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))
#else
#define FT_FX_CLONES
#endif

/* Per-pixel thresholds of n pixels; mask NULL: every pixel used. */
typedef struct {
    float a, a1, ns, dt, maxv;
    int bright, dark;
} thr_cfg;

void ft_fx_thresh8(size_t n, const float *restrict mean, const float *restrict sumsq,
                   const uint8_t *restrict mask, uint8_t *restrict hi, uint8_t *restrict lo,
                   thr_cfg c);
void ft_fx_thresh16(size_t n, const float *restrict mean, const float *restrict sumsq,
                    const uint8_t *restrict mask, uint16_t *restrict hi, uint16_t *restrict lo,
                    thr_cfg c);

/* Per block of blk pixels of one row of w: the lowest hi and the highest lo that can follow the
 * next background update (see thresholds.c). */
void ft_fx_next_bounds8(size_t w, size_t blk, const float *restrict mean, uint8_t *restrict nbhi,
                        uint8_t *restrict nblo, thr_cfg c);
void ft_fx_next_bounds16(size_t w, size_t blk, const float *restrict mean, uint16_t *restrict nbhi,
                         uint16_t *restrict nblo, thr_cfg c);

#endif
