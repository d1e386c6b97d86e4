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

#endif
