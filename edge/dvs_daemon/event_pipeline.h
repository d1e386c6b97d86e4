/* What flytrack-edge does with the events of an event source, one time slice at a time.
 *
 * The events of each slice (--slice-us of event time) go to an ft_event_processor, whose clusters
 * go out in one DVS_CLUSTERS datagram (protocol/SPEC.md 1.6) with the slice's first and last event
 * times. event_processor.c implements it with the event algorithms (edge/events/algos: noise
 * filters, then the cluster tracker with a Kalman filter per cluster); a slice without clusters
 * is still sent (n_clusters = 0), so the host sees the event time advance. */
#ifndef FLYTRACK_EDGE_EVENT_PIPELINE_H
#define FLYTRACK_EDGE_EVENT_PIPELINE_H

#include <stddef.h>
#include <stdint.h>

#include "flytrack/events.h"
#include "flytrack/udp.h"

typedef struct {
    void *ctx;
    /* Takes a slice's events (time-ordered), writes at most cap clusters, returns how many. */
    size_t (*slice)(void *ctx, const ft_event *ev, size_t n, int64_t t_start, int64_t t_end,
                    ft_dvs_cluster *out, size_t cap);
    void (*destroy)(void *ctx);
} ft_event_processor;

/* The processor flytrack-edge runs (width, height: the sensor). ba_window_us and min_mass (a
 * cluster's support to be reported) override the library's defaults when > 0: those (libcaer's
 * 2 ms, jAER-like 5 events over 10 ms) suit a DAVIS346-class sensor; on a smaller one an animal
 * crosses fewer pixels and gives fewer, sparser events (--ba-window-us, --cluster-min-mass). 0 or
 * -1. */
int ft_event_processor_create(ft_event_processor *p, uint32_t width, uint32_t height,
                              uint32_t ba_window_us, float min_mass);

#endif
