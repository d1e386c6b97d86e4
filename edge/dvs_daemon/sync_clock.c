/* Sensor time -> trigger frame from sync events (see sync_clock.h). */
#include "sync_clock.h"

#include <math.h>
#include <string.h>

void ft_sync_init(ft_sync_clock *c) {
    memset(c, 0, sizeof *c);
}

static uint64_t kept(const ft_sync_clock *c) {
    return c->n < FT_SYNC_KEEP ? c->n : FT_SYNC_KEEP;
}

double ft_sync_period(const ft_sync_clock *c) {
    uint64_t k = kept(c);
    if (k < 2)
        return 0.0;
    uint64_t a = (c->n - k) % FT_SYNC_KEEP, b = (c->n - 1) % FT_SYNC_KEEP;
    double frames = (double)(c->frame[b] - c->frame[a]);
    return frames > 0 ? (double)(c->t[b] - c->t[a]) / frames : 0.0;
}

void ft_sync_add(ft_sync_clock *c, int64_t t_us) {
    uint64_t f = 0;
    if (c->n) {
        uint64_t last = (c->n - 1) % FT_SYNC_KEEP;
        int64_t dt = t_us - c->t[last];
        if (dt <= 0) { /* a sensor time reset, or a repeated pulse: not a frame */
            c->out_of_order++;
            return;
        }
        double p = ft_sync_period(c);
        uint64_t step = 1;
        if (p > 0 && (double)dt > 1.5 * p) { /* pulses the sensor missed */
            step = (uint64_t)llround((double)dt / p);
            c->missed += step - 1;
        }
        f = c->frame[last] + step;
    }
    c->t[c->n % FT_SYNC_KEEP] = t_us;
    c->frame[c->n % FT_SYNC_KEEP] = f;
    c->n++;
}

int ft_sync_frame(const ft_sync_clock *c, int64_t t_us, double *frame) {
    uint64_t k = kept(c);
    double p = ft_sync_period(c);
    if (k < 2 || !(p > 0))
        return 0;
    /* newest first: the latest sync at or before t_us */
    for (uint64_t j = 0; j < k; j++) {
        uint64_t i = (c->n - 1 - j) % FT_SYNC_KEEP;
        if (c->t[i] > t_us)
            continue;
        if (j == 0) { /* after the newest: extrapolate */
            *frame = (double)c->frame[i] + (double)(t_us - c->t[i]) / p;
        } else { /* between two known syncs */
            uint64_t nx = (c->n - j) % FT_SYNC_KEEP;
            *frame = (double)c->frame[i] + (double)(c->frame[nx] - c->frame[i]) *
                                               (double)(t_us - c->t[i]) /
                                               (double)(c->t[nx] - c->t[i]);
        }
        return 1;
    }
    uint64_t o = (c->n - k) % FT_SYNC_KEEP; /* before the oldest kept */
    *frame = (double)c->frame[o] + (double)(t_us - c->t[o]) / p;
    return 1;
}
