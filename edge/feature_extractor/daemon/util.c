/* Shared helpers of the flytrack-edge loops (see util.h). */
#include "util.h"

#include <arpa/inet.h>
#include <errno.h>
#include <stdarg.h>
#include <stdio.h>
#include <string.h>
#include <sys/socket.h>
#include <time.h>

void edge_log(const char *fmt, ...) {
    va_list ap;
    va_start(ap, fmt);
    fprintf(stderr, "flytrack-edge: ");
    vfprintf(stderr, fmt, ap);
    fputc('\n', stderr);
    va_end(ap);
}

uint64_t edge_mono_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (uint64_t)ts.tv_sec * 1000000000ull + (uint64_t)ts.tv_nsec;
}

void edge_send(int sock, const uint8_t *buf, size_t len, const struct sockaddr_in *to,
               uint32_t *seq, uint64_t *send_errors, int verbose) {
    if (sendto(sock, buf, len, 0, (const struct sockaddr *)to, sizeof *to) < 0) {
        if ((*send_errors)++ == 0 || verbose)
            edge_log("sendto %s:%d: %s (counted, going on)", inet_ntoa(to->sin_addr),
                     ntohs(to->sin_port), strerror(errno));
    }
    (*seq)++;
}
