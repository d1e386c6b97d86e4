/* Small pieces both flytrack-edge loops share (frames in edge_main.c, events in edge_dvs.c). */
#ifndef FLYTRACK_EDGE_UTIL_H
#define FLYTRACK_EDGE_UTIL_H

#include <netinet/in.h>
#include <stddef.h>
#include <stdint.h>

/* One line on stderr, prefixed "flytrack-edge: ". */
void edge_log(const char *fmt, ...) __attribute__((format(printf, 1, 2)));

/* CLOCK_MONOTONIC in nanoseconds: intervals only. */
uint64_t edge_mono_ns(void);

/* Sends one datagram; a failure is counted in *send_errors and logged the first time (every time
 * when verbose), and the sender goes on. *seq is +1 per datagram, sent or not (the SPEC's rule). */
void edge_send(int sock, const uint8_t *buf, size_t len, const struct sockaddr_in *to,
               uint32_t *seq, uint64_t *send_errors, int verbose);

#endif
