/* Wing beats of a tethered fly from its events, streaming (seed 002, part II): the same algorithm
 * as the host's flytrack_host.dvs.wingbeat (geometry.py, ekf.py, analysis.py), for the edge.
 *
 * Initialisation (once, on a buffer): the events of the first init_us of event time are kept;
 * pixels that fire at least 4 times in it are the beating wings' (noise fires once or twice);
 * 2-means on their positions (prototypes started at the upper-right and lower-left sensor corners)
 * gives the two wing centroids, the body is between them, the heading orthogonal to their line,
 * the tail on the side where more wing events fall; the fly's size is twice the body-to-centroid
 * distance, events outside it or within 0.15 of that distance of the body are ignored. Each wing's
 * mean event angle and half its 5-95 % angle range start its filters; the starting frequency comes
 * from the autocorrelation of the mean event angle in 0.1 ms bins (50-1000 Hz). When no fly is
 * found (too few events, no pixel firing repeatedly, one cluster, ...) ft_wb_last_error() says why
 * and the next init_us window is tried: a fly that starts beating later is still found.
 *
 * Tracking (per event, O(1)): the event's angle about the body from the heading (eq. 8) picks its
 * wing (side of the heading) and edge (OFF = leading, ON = trailing); each of the 4 edges has an
 * EKF on h = a + b1 sin(xi) + sum_{k=2..K} (b_k sin k xi + c_k cos k xi), state (a, b1, b2, c2,
 * ..., xi, omega), xi += omega dt with dt from the events' own times (events of the same time
 * update without a prediction), events_per_update consecutive events of an edge averaged into one
 * update, an innovation gate for noise. The buffered events are replayed through the filters once
 * the fly is found, so no event is lost to the initialisation. A beat of an edge ends when its
 * phase passes a multiple of 2 pi: its frequency (omega / 2 pi) and amplitude (half the range of h
 * over a beat) are reported (ft_wb_feed's beats). */
#ifndef FLYTRACK_WINGBEAT_H
#define FLYTRACK_WINGBEAT_H

#include <stddef.h>
#include <stdint.h>

#include "flytrack/events.h"

#ifdef __cplusplus
extern "C" {
#endif

#define FT_WB_MAX_HARMONICS 4

typedef struct {
    uint32_t width, height;
    uint32_t init_us;           /* initialisation window of event time (100000) */
    uint32_t init_max_events;   /* a window holding more is cut there (262144) */
    uint32_t harmonics;         /* K, 1..FT_WB_MAX_HARMONICS (2; 1 is the seed's sinusoid) */
    uint32_t events_per_update; /* (4) */
    double measurement_std_rad; /* one event's angle about its edge (0.06) */
    double q_centre;            /* rad^2/s (0.05) */
    double q_shape;             /* rad^2/s, amplitude and harmonics (1.0) */
    double q_phase;             /* rad^2/s (2.0) */
    double q_omega;             /* (rad/s)^2/s (4000) */
    double gate_sigma;          /* (4) */
    double initial_phase_std;   /* rad (pi) */
    double initial_freq_std_hz; /* (5) */
    double start_freq_hz;       /* 0: found in the initialisation window */
} ft_wb_params;

typedef struct {
    double body_x, body_y; /* px */
    double heading;        /* rad, from +x towards +y */
    double size_px, inner_px;
    double mean_stroke[2], spread[2]; /* per wing, rad from the heading */
    double start_freq_hz[2];
} ft_wb_geometry;

/* One beat of one edge. */
typedef struct {
    int64_t t_us; /* when it ended (the update's mean event time) */
    uint8_t wing; /* 0: on the +90 degree side of the heading in sensor coordinates, 1: the other */
    uint8_t edge; /* 0 leading (OFF events), 1 trailing (ON) */
    uint8_t pad[2];
    float freq_hz;
    float amplitude; /* rad */
} ft_wb_beat;

/* The current estimate of an edge, or of a wing (its two edges averaged). */
typedef struct {
    float angle;     /* rad from the heading: h at the current state */
    float amplitude; /* rad: half the range of h over a beat */
    float freq_hz;
    float phase; /* xi modulo 2 pi (a wing: its leading edge's) */
    uint64_t updates;
} ft_wb_estimate;

typedef struct {
    uint64_t events;                               /* fed */
    uint64_t in_roi;                               /* taken by an edge's filter */
    uint64_t updates, gated, beats, beats_dropped; /* dropped: no room in the caller's array */
    uint64_t init_attempts, init_failures;
    uint64_t bad_events; /* outside the sensor */
} ft_wb_stats;

enum { FT_WB_INITIALISING = 0, FT_WB_TRACKING = 1 };

typedef struct ft_wb_tracker ft_wb_tracker;

void ft_wb_defaults(ft_wb_params *p, uint32_t width, uint32_t height);
ft_wb_tracker *ft_wb_create(const ft_wb_params *p); /* NULL on bad parameters or no memory */
/* Feeds time-ordered events; writes the beats that ended (at most cap, more are counted as
 * dropped; beats may be NULL) and returns how many were written. */
size_t ft_wb_feed(ft_wb_tracker *t, const ft_event *ev, size_t n, ft_wb_beat *beats, size_t cap);
int ft_wb_state(const ft_wb_tracker *t);
/* Why the last initialisation window found no fly ("" when none failed); the counter rises with
 * each failure so a caller can tell a new one. */
const char *ft_wb_last_error(const ft_wb_tracker *t, uint64_t *failures);
int ft_wb_get_geometry(const ft_wb_tracker *t, ft_wb_geometry *g); /* 0 once tracking, else -1 */
/* out[wing * 2 + edge] */
void ft_wb_edges(const ft_wb_tracker *t, ft_wb_estimate out[4]);
/* out[wing]: angle, amplitude and frequency the mean of its two edges', phase its leading edge's;
 * an edge without updates yet is left out of the mean. */
void ft_wb_wings(const ft_wb_tracker *t, ft_wb_estimate out[2]);
void ft_wb_get_stats(const ft_wb_tracker *t, ft_wb_stats *s);
void ft_wb_destroy(ft_wb_tracker *t);

#ifdef __cplusplus
}
#endif
#endif
