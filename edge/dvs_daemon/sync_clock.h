/* Sensor time -> trigger frame, from the sync events an event camera records at every trigger
 * pulse (protocol/SPEC.md 1.6, trigger-frame stamp).
 *
 * Sync events are numbered 0, 1, 2, ... in the order they come; a gap of k measured periods counts
 * k - 1 missed pulses, so that the numbers stay trigger frames (sync 0 = trigger frame 0 when the
 * sensor saw the trigger's first pulse). The period is the mean over the latest FT_SYNC_KEEP syncs.
 * A time between two known syncs is interpolated; after the latest one (or before the oldest kept)
 * it is extrapolated with the period. O(1) per sync, O(FT_SYNC_KEEP) per query at worst. */
#ifndef FLYTRACK_EDGE_SYNC_CLOCK_H
#define FLYTRACK_EDGE_SYNC_CLOCK_H

#include <stdint.h>

#define FT_SYNC_KEEP 64

typedef struct {
    int64_t t[FT_SYNC_KEEP];      /* sensor times, us */
    uint64_t frame[FT_SYNC_KEEP]; /* their trigger frames */
    uint64_t n;                   /* syncs taken (ring index) */
    uint64_t missed;              /* pulses counted through gaps */
    uint64_t out_of_order;        /* syncs not after the previous one: ignored */
} ft_sync_clock;

void ft_sync_init(ft_sync_clock *c);
/* One sync event at sensor time t_us. */
void ft_sync_add(ft_sync_clock *c, int64_t t_us);
/* The measured period (us); 0 before two syncs. */
double ft_sync_period(const ft_sync_clock *c);
/* Trigger frame (with fraction) at sensor time t_us; returns 0 (nothing written) before two syncs.
 */
int ft_sync_frame(const ft_sync_clock *c, int64_t t_us, double *frame);

#endif
