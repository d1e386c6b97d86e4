/* Event algorithms of seed 002, part I, streaming with O(1) work per event: noise filters and a
 * cluster tracker with a linear Kalman filter on each cluster.
 *
 * Noise filters (defaults are libcaer's): an event survives when
 *   - background activity: one of its 8 neighbours fired within ba_window_us (2 ms);
 *   - spatio-temporal correlation: at least stc_min_neighbours of its 8 neighbours fired within
 *     ba_window_us (off by default; 1 is the background-activity filter counted per neighbour);
 *   - refractory: its own pixel's last surviving event is at least refractory_us ago (100 us);
 *   - hot pixel: its pixel is not hot; a pixel is hot once it fires hot_pixel_count events
 *     (10,000) within one hot_pixel_window_us (1 s) learning window.
 * Timestamps are kept per pixel as 32-bit microseconds, compared modulo 2^32 (so a recording may be
 * any length; a gap of more than 35 minutes between two events of a pixel reads as recent once).
 *
 * Cluster tracker (jAER's rectangular cluster tracker, as seed 002 eq. 1 describes): an event
 * inside a cluster (within its radius) moves the nearest such cluster towards it,
 * x = (1 - m) x + m x_event (m = mixing, 0.05); an event outside every cluster starts a new one (up
 * to max_clusters, 10) of the a priori radius (0.1 of the sensor's larger side). Each cluster's
 * mass is its event count decayed with mass_decay_us (10 ms); a cluster whose mass falls under
 * min_mass has no support and dies. Two clusters closer than the mean of their radii merge, unless
 * their velocities differ by more than merge_max_dv (the seed's suggestion), so two animals that
 * cross keep their clusters. Velocities are the low-passed motion of each cluster's centre.
 *
 * Kalman filter (seed 002 part I, eqs 2-6): on each cluster, state (y, y', x, x'), constant
 * velocity, the cluster's position as the measurement, one update per kf_interval_us of event time.
 * Options as the seed's appendix: feedback to the cluster (its position set to the filter's),
 * dynamic variances (measurement variance grows from a tenth of max_meas_var to max_meas_var and
 * process variance falls from 10 x min_proc_var to min_proc_var over the first kf_ramp updates),
 * and events until tracking starts (filters launched once that many events were processed).
 * kf_centroid (on by default) measures the events' centroid per tick instead of the centre. The
 * clusters are reported with the filter predicted to the time asked for, and its position
 * covariance. */
#ifndef FLYTRACK_EVENT_ALGOS_H
#define FLYTRACK_EVENT_ALGOS_H

#include <stddef.h>
#include <stdint.h>

#include "flytrack/events.h"

#ifdef __cplusplus
extern "C" {
#endif

typedef struct {
    uint32_t width, height;
    uint32_t ba_window_us;        /* 0: background-activity filter off */
    uint32_t stc_min_neighbours;  /* 0: correlation filter off; 1..8 */
    uint32_t refractory_us;       /* 0: off */
    uint32_t hot_pixel_count;     /* 0: off */
    uint32_t hot_pixel_window_us; /* learning window */
} ft_nf_params;

typedef struct {
    uint64_t in, out;
    uint64_t ba_removed, stc_removed, refractory_removed, hot_removed;
    uint32_t hot_pixels;
} ft_nf_stats;

typedef struct ft_noise_filter ft_noise_filter;

void ft_nf_defaults(ft_nf_params *p, uint32_t width, uint32_t height);
ft_noise_filter *ft_nf_create(const ft_nf_params *p); /* NULL on bad parameters or no memory */
/* Filters ev[0..n) in place (survivors moved to the front, order kept); returns how many survive.
 * Events outside the sensor are removed (counted as ba_removed: they cannot have neighbours). */
size_t ft_nf_apply(ft_noise_filter *f, ft_event *ev, size_t n);
void ft_nf_get_stats(const ft_noise_filter *f, ft_nf_stats *s);
void ft_nf_destroy(ft_noise_filter *f);

#define FT_CT_MAX_CLUSTERS 64

typedef struct {
    uint32_t width, height;
    uint32_t max_clusters; /* <= FT_CT_MAX_CLUSTERS */
    float radius_px;       /* a priori cluster radius */
    float mixing;          /* m of eq. 1 */
    uint32_t mass_decay_us;
    float min_mass;        /* support below which a cluster dies */
    float merge_max_dv;    /* px/s; clusters moving apart faster than this do not merge */
    float velocity_tau_us; /* low-pass of the cluster velocity */
    /* Kalman filter */
    int kalman; /* 0: off */
    uint32_t kf_interval_us;
    int feedback; /* set the cluster's position to the filter's after each update */
    int dynamic_variances;
    uint32_t kf_ramp; /* updates over which dynamic variances reach their end values */
    uint64_t events_until_track;
    float max_meas_var; /* px^2 */
    float min_proc_var; /* (px/s)^2 per second, on the velocities */
    /* 1: the filter measures the centroid of the events a cluster took since the last tick, with
     * their spread over their number as the variance (the centre trails a moving animal by about
     * (1 - m) / m events); 0: the cluster's centre with max_meas_var, as the seed */
    int kf_centroid;
    /* px^2 added to each axis of a reported position covariance with kf_centroid: the centroid of
     * an animal's events is not its centre (the leading and trailing edges fire unevenly), an error
     * that moves with the animal, so averaging does not shrink it. 0.5 makes the normalised error
     * of the simulated rig's clusters 1.94 on average (3 animals, 5 s; 2 expected, 2 axes). */
    float centroid_var;
    /* kf_centroid: once a cluster's filter runs, only events within 3 sigma of the filter's
     * position (at least this radius, px) count towards the centroid; 0: all the cluster's events
     */
    float centroid_gate_px;
} ft_ct_params;

typedef struct {
    uint32_t id;
    float x, y;                 /* px: the filter's position when it runs, else the cluster's */
    float vx, vy;               /* px/s */
    float size;                 /* radius, px */
    float mass;                 /* decayed event count */
    float var_x, var_y, cov_xy; /* px^2: position covariance (the filter's at the time asked for,
                                 * else radius^2 / 4) */
    uint32_t events;            /* events the cluster has taken */
    int tracking;               /* 1 once its Kalman filter runs */
} ft_ct_cluster;

typedef struct {
    uint64_t events, created, died, merged, unassigned, kf_updates;
} ft_ct_stats;

typedef struct ft_cluster_tracker ft_cluster_tracker;

void ft_ct_defaults(ft_ct_params *p, uint32_t width, uint32_t height);
ft_cluster_tracker *ft_ct_create(const ft_ct_params *p);
/* Feeds time-ordered events (already noise-filtered). */
void ft_ct_feed(ft_cluster_tracker *t, const ft_event *ev, size_t n);
/* The live clusters at event time t_us (masses decayed to it); at most cap written, returns how
 * many. Clusters without support are removed first. */
size_t ft_ct_clusters(ft_cluster_tracker *t, int64_t t_us, ft_ct_cluster *out, size_t cap);
void ft_ct_get_stats(const ft_cluster_tracker *t, ft_ct_stats *s);
void ft_ct_destroy(ft_cluster_tracker *t);

#ifdef __cplusplus
}
#endif
#endif
