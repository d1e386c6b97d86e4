/* flytrack-edge for event sources (--source dvs128 | events): events -> time slices -> the event
 * processor (event_pipeline.h) -> DVS_CLUSTERS datagrams, plus STATUS and CONTROL as for cameras.
 *
 * STATUS for an event source: frames_seen counts events, frames_dropped the events lost (garbage
 * words of a DVS128), fps is events per second over the last second, proc_us_* the processing time
 * per slice; width/height are the sensor's; state is ERROR while a DVS128 is unplugged (RUNNING
 * again once it is back). CONTROL: START, STOP, SET_PARAM slice_us; other commands answer FAILED.
 * With --wingbeat 1 the events go to the wing-beat tracker instead and DVS_WINGBEAT datagrams go
 * out (edge_wingbeat.h).
 */
#define _POSIX_C_SOURCE 200809L
#include <arpa/inet.h>
#include <errno.h>
#include <math.h>
#include <netinet/in.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

#include "config.h"
#include "edge_dvs.h"
#include "edge_wingbeat.h"
#include "event_pipeline.h"
#include "util.h"
#include "flytrack/udp.h"
#include "source_events.h"
#include "sync_clock.h"

#define POLL_MS 5
#define SLICE_CAP 65536 /* events held per slice; a fuller slice is cut early */

static volatile sig_atomic_t g_stop;
static void on_signal(int sig) {
    (void)sig;
    g_stop = 1;
}

typedef struct {
    const edge_config *cfg;
    ft_ev_source src;
    ft_event_processor proc;
    int sock;
    struct sockaddr_in host;
    uint32_t seq;
    uint8_t state;
    int64_t slice_us;
    uint64_t events, slices, send_errors;
    uint64_t control_rejected; /* CONTROL datagrams from senders not in --control-allow */
    uint64_t control_errors;   /* malformed CONTROL datagrams */
    uint32_t last_error_code;
    char last_error[FT_STATUS_ERROR_LEN + 1];
    ft_event *slice;
    size_t n_slice;
    uint64_t win_start_ns, win_events, win_slices;
    double win_us_sum, win_us_max;
    float rate, proc_mean, proc_max;
    ft_dvs_cluster clusters[FT_DVS_MAX_CLUSTERS];
    /* trigger frames from the source's sync events (SPEC 1.6 stamp); a slice is cut at each sync */
    ft_sync_clock clock;
    uint64_t syncs_taken;
    int64_t cut_sync;  /* the latest sync time a slice was cut at (or passed) */
    edge_wingbeat *wb; /* --wingbeat 1: wing beats instead of clusters */
} dvs_edge;

static void set_error(dvs_edge *e, uint32_t code, const char *text) {
    e->last_error_code = code;
    snprintf(e->last_error, sizeof e->last_error, "%.64s", text);
}

static void send_to(dvs_edge *e, const uint8_t *buf, size_t len, const struct sockaddr_in *to) {
    edge_send(e->sock, buf, len, to, &e->seq, &e->send_errors, e->cfg->verbose);
}

static void send_status(dvs_edge *e) {
    ft_status m;
    memset(&m, 0, sizeof m);
    m.camera_index = (uint16_t)e->cfg->camera_index;
    m.width = (uint16_t)e->src.width;
    m.height = (uint16_t)e->src.height;
    m.state = e->state;
    m.seq = e->seq;
    m.last_error_code = e->last_error_code;
    m.frames_seen = e->events;
    m.frames_dropped = e->src.lost;
    m.fps = e->rate;
    m.proc_us_mean = e->proc_mean;
    m.proc_us_max = e->proc_max;
    snprintf(m.camera_name, sizeof m.camera_name, "%.32s", e->cfg->camera_name);
    snprintf(m.last_error, sizeof m.last_error, "%.64s", e->last_error);
    uint8_t buf[FT_UDP_MAX_DATAGRAM];
    size_t len;
    if (ft_status_encode(buf, sizeof buf, &m, &len) == FT_OK)
        send_to(e, buf, len, &e->host);
}

/* Syncs the source has seen since the last call go into the clock. */
static void take_syncs(dvs_edge *e) {
    if (e->src.triggers - e->syncs_taken >
        FT_SRC_SYNC_RING) /* overwritten: the clock counts the gap */
        e->syncs_taken = e->src.triggers - FT_SRC_SYNC_RING;
    for (; e->syncs_taken < e->src.triggers; e->syncs_taken++)
        ft_sync_add(&e->clock, e->src.sync_t[e->syncs_taken % FT_SRC_SYNC_RING]);
}

/* The earliest sync after the last cut, or INT64_MAX. */
static int64_t next_cut(const dvs_edge *e) {
    int64_t best = INT64_MAX;
    uint64_t k = e->clock.n < FT_SYNC_KEEP ? e->clock.n : FT_SYNC_KEEP;
    for (uint64_t j = 0; j < k; j++) {
        int64_t ts = e->clock.t[(e->clock.n - 1 - j) % FT_SYNC_KEEP];
        if (ts <= e->cut_sync)
            break;
        best = ts;
    }
    return best;
}

static void wb_send(void *ctx, const uint8_t *buf, size_t len) {
    dvs_edge *e = ctx;
    send_to(e, buf, len, &e->host);
}

/* Processes and sends the slice held, if any; its clusters are stated at t_end (the slice's last
 * event, or the sync event that closes it). */
static void flush_slice_at(dvs_edge *e, int64_t t_end) {
    if (!e->n_slice)
        return;
    uint64_t t0 = edge_mono_ns();
    int64_t ts = e->slice[0].t, te = t_end;
    size_t nc =
        e->proc.slice(e->proc.ctx, e->slice, e->n_slice, ts, te, e->clusters, FT_DVS_MAX_CLUSTERS);
    double us = (double)(edge_mono_ns() - t0) / 1000.0;
    ft_dvs_clusters_hdr h;
    memset(&h, 0, sizeof h);
    h.camera_index = (uint16_t)e->cfg->camera_index;
    h.n_clusters = (uint16_t)(nc > FT_DVS_MAX_CLUSTERS ? FT_DVS_MAX_CLUSTERS : nc);
    h.seq = e->seq;
    h.t_start_us = (uint64_t)ts;
    h.t_end_us = (uint64_t)te;
    h.syncs = (uint32_t)e->clock.n;
    double frame;
    if (ft_sync_frame(&e->clock, te, &frame) && isfinite(frame)) {
        h.flags = FT_DVS_SYNCED;
        h.trigger_frame = frame;
        h.frame_period_us = (float)ft_sync_period(&e->clock);
    }
    struct timespec rt;
    clock_gettime(CLOCK_REALTIME, &rt);
    h.edge_done_ns = (uint64_t)rt.tv_sec * 1000000000ull + (uint64_t)rt.tv_nsec;
    uint8_t buf[FT_UDP_MAX_DATAGRAM];
    size_t len;
    ft_err r = ft_dvs_clusters_encode(buf, sizeof buf, &h, e->clusters, &len);
    if (r == FT_OK)
        send_to(e, buf, len, &e->host);
    else
        set_error(e, 50, "DVS_CLUSTERS encode failed (non-finite cluster)");
    e->slices++;
    e->win_slices++;
    e->win_us_sum += us;
    if (us > e->win_us_max)
        e->win_us_max = us;
    e->n_slice = 0;
}

static void flush_slice(dvs_edge *e) {
    if (e->wb) { /* --wingbeat 1: the wing-beat tracker reports on its own clock */
        edge_wb_flush(e->wb);
        return;
    }
    if (e->n_slice)
        flush_slice_at(e, e->slice[e->n_slice - 1].t);
}

/* Every event up to the latest sync is in (the source delivered all it decoded): cut there now
 * rather than wait for a later event to close the slice. */
static void cut_at_sync(dvs_edge *e) {
    if (!e->clock.n)
        return;
    int64_t s = e->clock.t[(e->clock.n - 1) % FT_SYNC_KEEP];
    if (s <= e->cut_sync)
        return;
    if (e->n_slice && e->slice[e->n_slice - 1].t <= s)
        flush_slice_at(e, s);
    e->cut_sync = s;
}

static void take_events(dvs_edge *e, const ft_event *ev, size_t n) {
    if (e->wb) { /* the whole batch to the wing-beat tracker; its time counts as a slice's */
        uint64_t t0 = edge_mono_ns();
        const char *news = edge_wb_take(e->wb, ev, n);
        double us = (double)(edge_mono_ns() - t0) / 1000.0;
        if (news)
            set_error(e, news[0] ? 42 : 0, news);
        e->slices++;
        e->win_slices++;
        e->win_us_sum += us;
        if (us > e->win_us_max)
            e->win_us_max = us;
        return;
    }
    int64_t s = next_cut(e);
    for (size_t i = 0; i < n; i++) {
        while (ev[i].t > s) { /* a sync before this event: the slice ends there */
            if (e->n_slice && e->slice[0].t <= s)
                flush_slice_at(e, s);
            e->cut_sync = s;
            s = next_cut(e);
        }
        if (e->n_slice && (ev[i].t - e->slice[0].t >= e->slice_us || e->n_slice == SLICE_CAP))
            flush_slice(e);
        e->slice[e->n_slice++] = ev[i];
    }
}

static void ack(dvs_edge *e, const struct sockaddr_in *to, uint32_t req, uint8_t cmd,
                uint8_t status, const char *msg) {
    ft_control_ack a;
    memset(&a, 0, sizeof a);
    a.request_id = req;
    a.camera_index = (uint16_t)e->cfg->camera_index;
    a.command = cmd;
    a.status = status;
    snprintf(a.message, sizeof a.message, "%.48s", msg);
    uint8_t buf[FT_UDP_HEADER + FT_CONTROL_ACK_SIZE];
    size_t len;
    if (ft_control_ack_encode(buf, sizeof buf, &a, &len) == FT_OK)
        send_to(e, buf, len, to);
}

static void poll_control(dvs_edge *e) {
    uint8_t buf[2048];
    for (;;) {
        struct sockaddr_in from;
        socklen_t fl = sizeof from;
        ssize_t n = recvfrom(e->sock, buf, sizeof buf, MSG_DONTWAIT, (struct sockaddr *)&from, &fl);
        if (n < 0)
            return;
        if (fl < sizeof from || from.sin_family != AF_INET ||
            !edge_config_control_allowed(e->cfg, from.sin_addr.s_addr)) {
            /* as the frame edge: said once (and in STATUS), then only counted; the count at exit */
            if (e->control_rejected++ == 0) {
                char text[96];
                snprintf(text, sizeof text, "CONTROL from %s dropped: not in --control-allow",
                         inet_ntoa(from.sin_addr));
                edge_log("%s (further ones are only counted)", text);
                set_error(e, 21, text);
            }
            continue;
        }
        ft_control c;
        ft_err r = ft_control_decode(buf, (size_t)n, &c);
        if (r != FT_OK) {
            char text[96];
            snprintf(text, sizeof text, "malformed CONTROL from %s: %s", inet_ntoa(from.sin_addr),
                     ft_err_name(r));
            /* a flood must not flood the log: the first ten, then every thousandth */
            if (++e->control_errors <= 10 || e->control_errors % 1000 == 0)
                edge_log("%s (ignored; %llu so far)", text, (unsigned long long)e->control_errors);
            set_error(e, 20, text);
            continue;
        }
        if (c.camera_index != FT_CAMERA_ANY && c.camera_index != e->cfg->camera_index) {
            ack(e, &from, c.request_id, c.command, FT_ACK_FAILED, "not this camera");
        } else if (c.command == FT_CMD_START) {
            e->state = FT_STATE_RUNNING;
            ack(e, &from, c.request_id, c.command, FT_ACK_OK, "running");
        } else if (c.command == FT_CMD_STOP) {
            flush_slice(e);
            e->state = FT_STATE_STOPPED;
            ack(e, &from, c.request_id, c.command, FT_ACK_OK, "stopped");
        } else if (c.command == FT_CMD_SET_PARAM && !strcmp(c.param, "slice_us")) {
            if (c.value < 1 || c.value > 10e6 || c.value != floor(c.value)) {
                ack(e, &from, c.request_id, c.command, FT_ACK_BAD_VALUE, "slice_us: 1..10000000");
            } else {
                e->slice_us = (int64_t)c.value;
                ack(e, &from, c.request_id, c.command, FT_ACK_OK, "slice_us set");
            }
        } else if (c.command == FT_CMD_SET_PARAM) {
            ack(e, &from, c.request_id, c.command, FT_ACK_UNKNOWN_PARAM, c.param);
        } else {
            ack(e, &from, c.request_id, c.command, FT_ACK_FAILED, "not for an event source");
        }
    }
}

static int open_socket(dvs_edge *e) {
    e->sock = socket(AF_INET, SOCK_DGRAM, 0);
    if (e->sock < 0)
        return -1;
    struct sockaddr_in a;
    memset(&a, 0, sizeof a);
    a.sin_family = AF_INET;
    a.sin_port = htons((uint16_t)e->cfg->control_port);
    if (inet_pton(AF_INET, e->cfg->bind, &a.sin_addr) != 1) {
        edge_log("--bind %s is not an IPv4 address", e->cfg->bind);
        return -1;
    }
    if (bind(e->sock, (struct sockaddr *)&a, sizeof a) < 0) {
        edge_log("cannot bind %s:%d for CONTROL: %s", e->cfg->bind, e->cfg->control_port,
                 strerror(errno));
        return -1;
    }
    memset(&e->host, 0, sizeof e->host);
    e->host.sin_family = AF_INET;
    e->host.sin_port = htons((uint16_t)e->cfg->port);
    if (inet_pton(AF_INET, e->cfg->host, &e->host.sin_addr) != 1) {
        edge_log("--host %s is not an IPv4 address", e->cfg->host);
        return -1;
    }
    int sz = 4 << 20;
    setsockopt(e->sock, SOL_SOCKET, SO_SNDBUF, &sz, sizeof sz);
    return 0;
}

int edge_is_event_source(const char *source) {
    return !strcmp(source, "dvs128") || !strcmp(source, "events");
}

void edge_dvs_stop(void) {
    g_stop = 1;
}

int edge_dvs_run(edge_config *cfg, const ft_usb_ops *usb) {
    static dvs_edge e;
    static ft_event in[8192];
    memset(&e, 0, sizeof e);
    g_stop = 0;
    e.cfg = cfg;
    e.slice_us = cfg->slice_us;
    ft_sync_init(&e.clock);
    e.cut_sync = INT64_MIN;
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    sigaction(SIGINT, &sa, NULL);
    sigaction(SIGTERM, &sa, NULL);
    signal(SIGPIPE, SIG_IGN);
    if (open_socket(&e))
        return 2;
    edge_config_default_control(cfg, e.host.sin_addr.s_addr);
    int rc;
    if (!strcmp(cfg->source, "events"))
        rc = ft_ev_source_open_file(&e.src, cfg->input, cfg->event_format, cfg->realtime);
    else
        rc = ft_ev_source_open_dvs128(&e.src, usb, cfg->have_dvs_biases ? cfg->dvs_biases : NULL,
                                      cfg->reopen_ms);
    e.src.invert_polarity = cfg->dvs_invert_polarity;
    if (rc) {
        edge_log("source %s %s: %s", cfg->source, cfg->input, e.src.error);
        close(e.sock);
        return 3;
    }
    e.slice = malloc(SLICE_CAP * sizeof *e.slice);
    if (!e.slice ||
        ft_event_processor_create(&e.proc, e.src.width, e.src.height, (uint32_t)cfg->ba_window_us,
                                  (float)cfg->cluster_min_mass) != 0) {
        edge_log("cannot set up the event processor");
        e.src.close(&e.src);
        close(e.sock);
        free(e.slice);
        return 2;
    }
    if (cfg->wingbeat &&
        !(e.wb = edge_wb_create(cfg, e.src.width, e.src.height, &e.seq, wb_send, &e))) {
        e.proc.destroy(e.proc.ctx);
        e.src.close(&e.src);
        close(e.sock);
        free(e.slice);
        return 2;
    }
    e.state = cfg->start_stopped ? FT_STATE_IDLE : FT_STATE_RUNNING;
    edge_log("%s %s: %ux%u sensor, slices of %lld us -> %s:%d, control on port %d", cfg->source,
             cfg->input, e.src.width, e.src.height, (long long)e.slice_us, cfg->host, cfg->port,
             cfg->control_port);
    e.win_start_ns = edge_mono_ns();
    send_status(&e);
    uint64_t last_status = edge_mono_ns(), last_event_ns = edge_mono_ns();
    int live = !strcmp(cfg->source, "dvs128");
    int exit_code = 0;
    while (!g_stop) {
        long n = e.src.next(&e.src, in, sizeof in / sizeof in[0], POLL_MS);
        uint64_t now = edge_mono_ns();
        if (n >= 0)
            take_syncs(&e);
        if (n > 0) {
            e.events += (uint64_t)n;
            e.win_events += (uint64_t)n;
            last_event_ns = now;
            if (e.state == FT_STATE_RUNNING)
                take_events(&e, in, (size_t)n);
        }
        if (n >= 0 && e.src.drained && e.state == FT_STATE_RUNNING)
            cut_at_sync(&e);
        if (n == FT_SRC_END) {
            edge_log("source ended after %llu events", (unsigned long long)e.events);
            break;
        } else if (n == FT_SRC_ERROR) {
            edge_log("source failed after %llu events: %s", (unsigned long long)e.events,
                     e.src.error);
            flush_slice(&e);
            e.state = FT_STATE_ERROR;
            /* STATUS has 64 characters: the message without the file name it starts with */
            size_t il = strlen(cfg->input);
            const char *msg = e.src.error;
            if (!strncmp(msg, cfg->input, il) && msg[il] == ':')
                msg += il + 2;
            set_error(&e, 40, msg);
            exit_code = 3;
            break;
        }
        if (e.src.state_changed) { /* a DVS128 unplugged or back */
            e.src.state_changed = 0;
            if (e.src.connected) {
                edge_log("DVS128 back (reconnect %llu)", (unsigned long long)e.src.reconnects);
                if (e.state == FT_STATE_ERROR)
                    e.state = FT_STATE_RUNNING;
                set_error(&e, 0, "");
            } else {
                edge_log("%s", e.src.error);
                flush_slice(&e);
                e.state = FT_STATE_ERROR;
                set_error(&e, 41, e.src.error);
                send_status(&e);
            }
        }
        /* a live sensor gone quiet: do not hold its last slice (a file's slices are cut by event
         * time only, so that they are the same at any playback speed) */
        if (live && e.n_slice && now - last_event_ns > 4ull * POLL_MS * 1000000ull)
            flush_slice(&e);
        poll_control(&e);
        double dt = (double)(now - e.win_start_ns) / 1e9;
        if (dt >= 1.0) {
            e.rate = (float)(e.win_events / dt);
            e.proc_mean = e.win_slices ? (float)(e.win_us_sum / e.win_slices) : 0.0f;
            e.proc_max = (float)e.win_us_max;
            e.win_start_ns = now;
            e.win_events = e.win_slices = 0;
            e.win_us_sum = e.win_us_max = 0;
        }
        if (now - last_status >= (uint64_t)cfg->status_interval_ms * 1000000ull) {
            send_status(&e);
            last_status = now;
        }
    }
    flush_slice(&e);
    if (e.state != FT_STATE_ERROR)
        e.state = FT_STATE_STOPPED;
    send_status(&e); /* the last word: counts and why we stopped */
    edge_log("%llu events in %llu slices sent, %llu garbage words, %llu reconnects",
             (unsigned long long)e.events, (unsigned long long)e.slices,
             (unsigned long long)e.src.lost, (unsigned long long)e.src.reconnects);
    if (e.control_rejected || e.control_errors)
        edge_log(
            "CONTROL: %llu datagrams from senders not in --control-allow dropped, %llu malformed",
            (unsigned long long)e.control_rejected, (unsigned long long)e.control_errors);
    if (e.wb) {
        edge_wb_log_summary(e.wb);
        edge_wb_destroy(e.wb);
    }
    e.src.close(&e.src);
    if (e.proc.destroy)
        e.proc.destroy(e.proc.ctx);
    free(e.slice);
    close(e.sock);
    return exit_code;
}
