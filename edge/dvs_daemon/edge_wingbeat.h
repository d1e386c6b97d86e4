/* flytrack-edge --wingbeat 1: the events of an event source go to the wing-beat tracker
 * (edge/events/algos/wingbeat.c, flytrack/wingbeat.h) instead of the cluster tracker, and a
 * DVS_WINGBEAT datagram (protocol/SPEC.md 1.7) goes out every --wingbeat-report-us of event time:
 * records 0 and 1 are the wings (angle, amplitude and frequency the mean of their two edges', phase
 * the leading edge's), records 2-5 the edges (wing 0 leading, wing 0 trailing, wing 1 leading,
 * wing 1 trailing). While the fly is not found yet the datagrams carry no records (the host sees
 * the edge alive and its event time advance), and each initialisation window that found no fly is
 * logged with the reason, which STATUS carries as its last error (code 42; cleared once the fly is
 * found). STATUS's proc_us_* are then the tracker's time per batch of events read. */
#ifndef FLYTRACK_EDGE_WINGBEAT_H
#define FLYTRACK_EDGE_WINGBEAT_H

#include <stddef.h>
#include <stdint.h>

#include "config.h"
#include "flytrack/events.h"

typedef struct edge_wingbeat edge_wingbeat;
/* Sends one encoded datagram (the caller's socket, counting *seq). */
typedef void (*edge_wb_send_fn)(void *ctx, const uint8_t *buf, size_t len);

/* NULL with a logged reason on bad parameters. seq: the sender's datagram counter (read only). */
edge_wingbeat *edge_wb_create(const edge_config *cfg, uint32_t width, uint32_t height,
                              const uint32_t *seq, edge_wb_send_fn send, void *ctx);
/* Feeds time-ordered events, sending the reports that fall due. Returns a message when an
 * initialisation window failed during this call ("" when the fly was just found), else NULL. */
const char *edge_wb_take(edge_wingbeat *w, const ft_event *ev, size_t n);
/* Sends a last report at the last event's time if events came since the last one. */
void edge_wb_flush(edge_wingbeat *w);
void edge_wb_log_summary(const edge_wingbeat *w);
void edge_wb_destroy(edge_wingbeat *w);

#endif
