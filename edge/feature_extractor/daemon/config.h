/* flytrack-edge configuration: defaults, TOML file, command-line flags (flags win). */
#ifndef FLYTRACK_EDGE_CONFIG_H
#define FLYTRACK_EDGE_CONFIG_H

#include <stdint.h>

#include "flytrack/features.h"

#define EDGE_MAX_CONTROL_ALLOW 16

typedef struct {
    char source[16]; /* raw, y4m, v4l2, aravis; event sources: events, dvs128 */
    char input[256]; /* path, "-" (stdin), /dev/videoN, camera name, or event file */
    uint32_t width, height;
    int pixel_format; /* -1: the source's */
    double fps;
    int vanish_timeout_ms;
    char host[64];
    int port;
    char bind[64];
    int control_port;
    int camera_index;
    char camera_name[33];
    int truncate; /* 1: truncate to 32 points instead of splitting */
    int start_stopped;
    int status_interval_ms;
    int region_half; /* SEND_REGIONS half-size, 0 = off */
    uint64_t max_frames;
    char mask[256];
    int verbose;
    ft_fx_params fx;      /* width/height/pixel_format filled once the source is open */
    double intrinsics[5]; /* fx fy cx cy skew */
    double distortion[5]; /* k1 k2 p1 p2 k3 */
    int have_intrinsics;
    /* CONTROL senders accepted (--control-allow); none given: the --host address and loopback. */
    uint32_t control_allow[EDGE_MAX_CONTROL_ALLOW]; /* IPv4, network byte order */
    int n_control_allow;
    int control_allow_any;      /* "any": every sender */
    int control_allow_loopback; /* "loopback": 127.0.0.0/8 */
    /* event sources (edge_dvs.c) */
    char event_format[16];   /* events: auto, aedat2, aedat3, aedat4, evt2, evt3, dat */
    int64_t slice_us;        /* events per DVS_CLUSTERS slice, in event time */
    int64_t ba_window_us;    /* background-activity window; 0: the library's (2 ms) */
    double cluster_min_mass; /* a cluster's support to be reported; 0: the library's (5) */
    int realtime;            /* events: play the file at its recorded pace */
    int reopen_ms;           /* dvs128: retry period while unplugged */
    uint8_t dvs_biases[36];
    int have_dvs_biases;
    int dvs_invert_polarity; /* dvs128: raw bit 0 = 1 means OFF (an original DVS128, as jAER) */
    /* event sources, --wingbeat 1: DVS_WINGBEAT instead of DVS_CLUSTERS (edge_wingbeat.c) */
    int wingbeat;
    int64_t wingbeat_report_us;
    int wingbeat_harmonics;
    int wingbeat_events_per_update;
    int64_t wingbeat_init_us;
    double wingbeat_start_freq;
} edge_config;

/* 0 = ok, 1 = --help printed, -1 = error (message printed to stderr). */
int edge_config_load(edge_config *c, int argc, char **argv);

/* 1 if a CONTROL datagram from IPv4 address addr (network byte order) is accepted: "any", loopback
 * (127.0.0.0/8) when allowed, or one of the --control-allow addresses. */
int edge_config_control_allowed(const edge_config *c, uint32_t addr);

/* The default when no --control-allow was given: the --host address (network byte order) and
 * 127.0.0.0/8. Both daemons (frame and event camera) call it, so they accept the same senders. */
void edge_config_default_control(edge_config *c, uint32_t host_addr);

#endif
