/* flytrack-edge's event loop (edge_dvs.c) with --source dvs128 on a fake USB device (no DVS128 on
 * the build machine; the device is the seam, ft_usb_ops), under ASan + UBSan: the loop runs in a
 * thread and sends real UDP to a socket here. The device streams words, is unplugged, fails three
 * reopens, comes back and streams again. Checked on the wire: STATUS turns ERROR ("unplugged")
 * and back to RUNNING, DVS_CLUSTERS slices keep coming, and the last STATUS counts every event the
 * device sent. */
#define _POSIX_C_SOURCE 200809L
#include <arpa/inet.h>
#include <netinet/in.h>
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/time.h>
#include <time.h>
#include <unistd.h>

#include "config.h"
#include "edge_dvs.h"
#include "flytrack/udp.h"

#include "check.h" /* CHECK(), ft_test_failures: protocol/tests/check.h */

#define WORDS 30000
static uint8_t stream_bytes[4 * WORDS];
static size_t stream_len, unplug_at, pos;
static int present = 1, unplugged, failed_opens;
static uint64_t events_sent;

static void make_stream(void) {
    uint32_t ts = 0;
    for (size_t i = 0; i < WORDS; i++) {
        uint8_t *w = stream_bytes + 4 * i;
        ts += 7;
        if (ts > 0x3FFF) { /* WRAP word */
            ts -= 0x4000;
            w[0] = w[1] = 0;
            w[2] = 0;
            w[3] = 0x80;
            continue;
        }
        w[0] = (uint8_t)(((i * 13) % 128) << 1 | (i & 1));
        w[1] = (uint8_t)((i * 7) % 128);
        w[2] = (uint8_t)ts;
        w[3] = (uint8_t)(ts >> 8);
        events_sent++;
    }
    stream_len = 4 * WORDS;
    unplug_at = 4 * (WORDS / 2); /* a word boundary: every event of the stream is delivered */
}

static void sleep_ms(unsigned ms) {
    struct timespec ts = {(time_t)(ms / 1000), (long)(ms % 1000) * 1000000L};
    nanosleep(&ts, NULL);
}

static int f_init(void **ctx) {
    *ctx = NULL;
    return 0;
}
static void *f_open(void *ctx, uint16_t vid, uint16_t pid) {
    (void)ctx, (void)vid, (void)pid;
    if (!present) { /* three failed reopens, then it is back */
        if (++failed_opens >= 3)
            present = 1;
        return NULL;
    }
    return &pos;
}
static int f_control(void *h, uint8_t req, uint16_t value, const uint8_t *data, uint16_t len,
                     unsigned timeout_ms) {
    (void)h, (void)req, (void)value, (void)data, (void)len, (void)timeout_ms;
    return FT_USB_OK;
}
static int f_bulk(void *h, uint8_t ep, uint8_t *buf, int len, int *got, unsigned timeout_ms) {
    (void)h, (void)ep;
    *got = 0;
    if (!present)
        return FT_USB_NO_DEVICE;
    if (!unplugged && pos == unplug_at) {
        unplugged = 1;
        present = 0;
        return FT_USB_NO_DEVICE;
    }
    size_t n = 1000 + (pos * 7) % 999; /* words split across transfers */
    size_t limit = unplugged ? stream_len : unplug_at;
    if (n > limit - pos)
        n = limit - pos;
    if (n > (size_t)len)
        n = (size_t)len;
    if (n == 0) {
        sleep_ms(timeout_ms);
        return FT_USB_TIMEOUT;
    }
    memcpy(buf, stream_bytes + pos, n);
    pos += n;
    *got = (int)n;
    sleep_ms(1); /* a sensor, not a file: the stream takes a while */
    return FT_USB_OK;
}
static void f_close(void *h) {
    (void)h;
}
static const ft_usb_ops fake = {f_init, NULL, f_open, f_control, f_bulk, f_close};

static edge_config cfg;
static int run_rc = -1;
static void *runner(void *arg) {
    (void)arg;
    run_rc = edge_dvs_run(&cfg, &fake);
    return NULL;
}

int main(void) {
    make_stream();
    int rx = socket(AF_INET, SOCK_DGRAM, 0);
    struct sockaddr_in a;
    memset(&a, 0, sizeof a);
    a.sin_family = AF_INET;
    a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    socklen_t al = sizeof a;
    CHECK(bind(rx, (struct sockaddr *)&a, sizeof a) == 0);
    getsockname(rx, (struct sockaddr *)&a, &al);
    int sz = 8 << 20;
    setsockopt(rx, SOL_SOCKET, SO_RCVBUF, &sz, sizeof sz);
    struct timeval tv = {0, 20000};
    setsockopt(rx, SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof tv);
    char port[16];
    snprintf(port, sizeof port, "%d", ntohs(a.sin_port));
    char *argv[] = {"flytrack-edge",
                    "--source",
                    "dvs128",
                    "--port",
                    port,
                    "--control-port",
                    "0",
                    "--reopen-ms",
                    "20",
                    "--status-interval-ms",
                    "50",
                    "--camera-index",
                    "2"};
    CHECK(edge_config_load(&cfg, (int)(sizeof argv / sizeof argv[0]), argv) == 0);
    pthread_t th;
    pthread_create(&th, NULL, runner, NULL);
    int saw_error = 0, saw_running_after = 0, stopped = 0;
    uint64_t slices = 0, last_seen = 0, last_t_end = 0;
    int t_back = 0;
    for (int spins = 0; spins < 3000 && !stopped; spins++) { /* at most ~60 s */
        uint8_t buf[2048];
        ssize_t n = recv(rx, buf, sizeof buf, 0);
        if (n <= 0) {
            if (last_seen == events_sent && saw_running_after)
                edge_dvs_stop();
            continue;
        }
        uint8_t type;
        if (ft_peek_type(buf, (size_t)n, &type) != FT_OK)
            continue;
        if (type == FT_MSG_STATUS) {
            ft_status st;
            CHECK(ft_status_decode(buf, (size_t)n, &st) == FT_OK);
            CHECK(st.camera_index == 2 && st.width == 128 && st.height == 128);
            last_seen = st.frames_seen;
            if (st.state == FT_STATE_ERROR && strstr(st.last_error, "unplugged"))
                saw_error = 1;
            if (saw_error && st.state == FT_STATE_RUNNING)
                saw_running_after = 1;
            if (st.state == FT_STATE_STOPPED)
                stopped = 1;
        } else if (type == FT_MSG_DVS_CLUSTERS) {
            ft_dvs_clusters_hdr h;
            static ft_dvs_cluster c[FT_DVS_MAX_CLUSTERS];
            CHECK(ft_dvs_clusters_decode(buf, (size_t)n, &h, c) == FT_OK);
            CHECK(h.t_end_us >= h.t_start_us && h.t_end_us - h.t_start_us < 1000);
            if (h.t_start_us < last_t_end)
                t_back++; /* the device's clock restarted at the replug: once */
            last_t_end = h.t_end_us;
            slices++;
        }
    }
    pthread_join(th, NULL);
    CHECK(run_rc == 0);
    CHECK(saw_error && saw_running_after && stopped);
    CHECK(last_seen == events_sent);
    CHECK(slices > 10 && t_back == 1);
    CHECK(failed_opens == 3);
    close(rx);
    if (ft_test_failures) {
        fprintf(stderr, "test_edge_dvs_unplug: %d checks failed (events %llu of %llu)\n",
                ft_test_failures, (unsigned long long)last_seen, (unsigned long long)events_sent);
        return 1;
    }
    printf("test_edge_dvs_unplug: %llu events, %llu slices, unplugged and back\n",
           (unsigned long long)events_sent, (unsigned long long)slices);
    return 0;
}
