/* Internal: per-pixel candidate thresholds from the background model (see features.c). */
#ifndef FLYTRACK_FX_THRESHOLDS_H
#define FLYTRACK_FX_THRESHOLDS_H

#include <stddef.h>
#include <stdint.h>

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
