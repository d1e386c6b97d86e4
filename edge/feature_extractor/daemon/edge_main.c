/* flytrack-edge: frames -> libflytrack_features -> FEATURES datagrams (protocol/SPEC.md §1).
 *
 * One thread, one UDP socket (bound to --control-port): FEATURES, STATUS, CONTROL_ACK and IMAGE go
 * from it to the host, CONTROL comes in on it and is answered to its sender. The loop waits on the
 * source with a short timeout, so control messages and the heartbeat are served between frames.
 */
#include <arpa/inet.h>
#include <errno.h>
#include <math.h>
#include <netinet/in.h>
#include <signal.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

#include "config.h"
#include "util.h"
#include "edge_dvs.h"
#include "flytrack/features.h"
#include "flytrack/udp.h"
#include "source.h"

#define POLL_MS 5

static volatile sig_atomic_t g_stop;
static void on_signal(int sig) {
    (void)sig;
    g_stop = 1;
}

typedef struct {
    edge_config cfg;
    ft_source src;
    ft_fx *fx;
    int sock;
    struct sockaddr_in host;
    uint32_t seq;
    uint8_t state;
    uint64_t frames_seen, frames_dropped, control_errors, send_errors;
    uint64_t control_rejected; /* CONTROL datagrams from senders not in --control-allow */
    uint32_t last_error_code;
    char last_error[FT_STATUS_ERROR_LEN + 1];
    /* per-second statistics for STATUS */
    uint64_t win_start_ns, win_frames;
    double win_proc_us_sum, win_proc_us_max;
    float fps, proc_mean, proc_max;
    uint64_t last_status_ns;
    int pending_full; /* a full frame was asked for */
    uint32_t full_id;
    int region_half;
    uint32_t region_id;
    ft_point pts[FT_FEATURES_MAX_POINTS];
} edge;

static void set_error(edge *e, uint32_t code, const char *text) {
    e->last_error_code = code;
    snprintf(e->last_error, sizeof e->last_error, "%.64s", text);
}

static void send_to(edge *e, const uint8_t *buf, size_t len, const struct sockaddr_in *to) {
    edge_send(e->sock, buf, len, to, &e->seq, &e->send_errors, e->cfg.verbose);
}

static void send_status(edge *e) {
    ft_status m;
    memset(&m, 0, sizeof m);
    m.camera_index = (uint16_t)e->cfg.camera_index;
    m.width = (uint16_t)e->src.width;
    m.height = (uint16_t)e->src.height;
    m.pixel_format = (uint8_t)e->src.pixel_format;
    m.state = e->state;
    m.seq = e->seq;
    m.last_error_code = e->last_error_code;
    m.frames_seen = e->frames_seen;
    m.frames_dropped = e->frames_dropped + e->src.dropped;
    m.fps = e->fps;
    m.proc_us_mean = e->proc_mean;
    m.proc_us_max = e->proc_max;
    snprintf(m.camera_name, sizeof m.camera_name, "%.32s", e->cfg.camera_name);
    snprintf(m.last_error, sizeof m.last_error, "%.64s", e->last_error);
    uint8_t buf[FT_UDP_MAX_DATAGRAM];
    size_t len;
    ft_err r = ft_status_encode(buf, sizeof buf, &m, &len);
    if (r != FT_OK) {
        edge_log("cannot encode STATUS: %s", ft_err_name(r));
        return;
    }
    send_to(e, buf, len, &e->host);
}

static void send_image(edge *e, const ft_frame *f, uint8_t kind, uint32_t id, uint16_t x0,
                       uint16_t y0, uint16_t w, uint16_t h) {
    /* YUYV frames are sent as their luma (1 byte per pixel). */
    int yuyv = e->src.pixel_format == FT_FX_YUYV;
    uint8_t bpp = e->src.pixel_format == FT_FX_MONO16 ? 2 : 1;
    uint32_t row_bytes = (uint32_t)w * bpp, total = row_bytes * h;
    static uint8_t chunk[FT_IMAGE_MAX_CHUNK];
    uint8_t buf[FT_UDP_MAX_DATAGRAM];
    for (uint32_t off = 0; off < total;) {
        uint32_t n = total - off < FT_IMAGE_MAX_CHUNK ? total - off : FT_IMAGE_MAX_CHUNK;
        for (uint32_t k = 0; k < n; k++) { /* gather the chunk's bytes row by row */
            uint32_t b = off + k, row = b / row_bytes, col = b % row_bytes;
            size_t src_off = (size_t)(y0 + row) * e->src.stride;
            if (yuyv)
                chunk[k] = f->data[src_off + 2 * (size_t)(x0 + col)];
            else
                chunk[k] = f->data[src_off + (size_t)x0 * bpp + col];
        }
        ft_image m = {0,           (uint16_t)e->cfg.camera_index,
                      kind,        bpp,
                      id,          f->camera_frame,
                      x0,          y0,
                      w,           h,
                      off,         total,
                      (uint16_t)n, chunk};
        size_t len;
        ft_err r = ft_image_encode(buf, sizeof buf, &m, &len);
        if (r != FT_OK) {
            edge_log("cannot encode IMAGE: %s", ft_err_name(r));
            return;
        }
        send_to(e, buf, len, &e->host);
        off += n;
    }
}

static float clamp_f32(double v) {
    if (isnan(v))
        return (float)v;
    if (v > 3.0e38)
        return 3.0e38f;
    if (v < -3.0e38)
        return -3.0e38f;
    return (float)v;
}

static void send_features(edge *e, const ft_frame *f, const ft_fx_result *r) {
    uint32_t n = r->n_points;
    uint32_t total = r->total_points > 65535 ? 65535 : r->total_points;
    uint32_t parts = 1, per = n;
    uint16_t flags = 0;
    /* part_index/part_count are one byte: never more than 255 parts (the library caps max_points
     * at FT_FX_MAX_POINTS = 255 x 32 already; this guards the cast, whatever the caller set). */
    if (n > 255u * FT_FEATURES_MAX_POINTS)
        n = 255u * FT_FEATURES_MAX_POINTS;
    if (n > FT_FEATURES_MAX_POINTS) {
        if (e->cfg.truncate) {
            per = n = FT_FEATURES_MAX_POINTS;
        } else {
            parts = (n + FT_FEATURES_MAX_POINTS - 1) / FT_FEATURES_MAX_POINTS;
            per = FT_FEATURES_MAX_POINTS;
            flags |= FT_FEATURES_SPLIT;
        }
    }
    if (r->total_points > n)
        flags |= FT_FEATURES_TRUNCATED;
    uint8_t buf[FT_UDP_MAX_DATAGRAM];
    for (uint32_t part = 0; part < parts; part++) {
        uint32_t first = part * per, cnt = n - first < per ? n - first : per;
        for (uint32_t i = 0; i < cnt; i++) {
            const ft_fx_point *p = &r->points[first + i];
            ft_point *q = &e->pts[i];
            q->x_dist = clamp_f32(p->x_dist);
            q->y_dist = clamp_f32(p->y_dist);
            q->x_undist = clamp_f32(p->x_undist);
            q->y_undist = clamp_f32(p->y_undist);
            q->area = clamp_f32(p->area);
            q->peak_diff = clamp_f32(p->peak_diff);
            q->orientation = clamp_f32(p->orientation);
            q->eccentricity = clamp_f32(p->eccentricity);
            q->cur_val = (uint16_t)p->cur_val;
            q->mean_val = clamp_f32(p->mean_val);
            q->sumsq_val = clamp_f32(p->sumsq_val);
        }
        ft_features_hdr h;
        memset(&h, 0, sizeof h);
        h.flags = flags;
        h.camera_index = (uint16_t)e->cfg.camera_index;
        h.n_points = (uint16_t)cnt;
        h.seq = e->seq;
        h.camera_frame = f->camera_frame;
        h.trigger_frame = -1;
        h.device_timestamp_ns = f->device_timestamp_ns;
        h.edge_recv_ns = f->recv_ns;
        h.total_points = (uint16_t)total;
        h.part_index = (uint8_t)part;
        h.part_count = (uint8_t)parts;
        h.edge_done_ns = ft_now_ns();
        size_t len;
        ft_err er = ft_features_encode(buf, sizeof buf, &h, e->pts, &len);
        if (er != FT_OK) {
            edge_log("cannot encode FEATURES of frame %llu: %s",
                     (unsigned long long)f->camera_frame, ft_err_name(er));
            set_error(e, 10, "FEATURES encode failed");
            return;
        }
        send_to(e, buf, len, &e->host);
    }
}

static void ack(edge *e, const struct sockaddr_in *to, uint32_t req, uint8_t cmd, uint8_t status,
                const char *msg) {
    ft_control_ack a;
    memset(&a, 0, sizeof a);
    a.request_id = req;
    a.camera_index = (uint16_t)e->cfg.camera_index;
    a.command = cmd;
    a.status = status;
    snprintf(a.message, sizeof a.message, "%.48s", msg);
    uint8_t buf[FT_UDP_HEADER + FT_CONTROL_ACK_SIZE];
    size_t len;
    if (ft_control_ack_encode(buf, sizeof buf, &a, &len) == FT_OK)
        send_to(e, buf, len, to);
}

static void handle_control(edge *e, const uint8_t *buf, size_t len,
                           const struct sockaddr_in *from) {
    ft_control c;
    ft_err r = ft_control_decode(buf, len, &c);
    if (r != FT_OK) {
        e->control_errors++;
        char text[96];
        snprintf(text, sizeof text, "malformed CONTROL from %s: %s", inet_ntoa(from->sin_addr),
                 ft_err_name(r));
        /* A flood must not flood the log: the first ten, then every thousandth. */
        if (e->control_errors <= 10 || e->control_errors % 1000 == 0 || e->cfg.verbose)
            edge_log("%s (ignored; %llu so far)", text, (unsigned long long)e->control_errors);
        set_error(e, 20, text);
        /* The framing was right but a field was not: answer, so the sender is not left waiting. */
        if ((r == FT_E_BAD_FIELD || r == FT_E_NOT_FINITE) &&
            len == FT_UDP_HEADER + FT_CONTROL_SIZE) {
            uint8_t cmd = buf[FT_UDP_HEADER + 6];
            uint8_t st = (cmd < FT_CMD_SET_PARAM || cmd > FT_CMD_STOP) ? FT_ACK_UNKNOWN_COMMAND
                                                                       : FT_ACK_BAD_VALUE;
            ack(e, from, ft_ld_u32(buf + FT_UDP_HEADER), cmd, st, ft_err_name(r));
        }
        return;
    }
    if (e->cfg.verbose)
        edge_log("CONTROL %u command %u param '%s' value %g", c.request_id, c.command, c.param,
                 c.value);
    if (c.camera_index != FT_CAMERA_ANY && c.camera_index != e->cfg.camera_index) {
        ack(e, from, c.request_id, c.command, FT_ACK_FAILED, "not this camera");
        return;
    }
    char msg[64];
    switch (c.command) {
    case FT_CMD_SET_PARAM: {
        int rc = ft_fx_set_param(e->fx, c.param, c.value);
        if (rc == FT_FX_E_UNKNOWN_PARAM) {
            ack(e, from, c.request_id, c.command, FT_ACK_UNKNOWN_PARAM, c.param);
        } else if (rc) {
            snprintf(msg, sizeof msg, "%.24s: value out of range", c.param);
            ack(e, from, c.request_id, c.command, FT_ACK_BAD_VALUE, msg);
        } else {
            snprintf(msg, sizeof msg, "%.24s = %g", c.param, c.value);
            ack(e, from, c.request_id, c.command, FT_ACK_OK, msg);
        }
        return;
    }
    case FT_CMD_TAKE_BACKGROUND:
        ft_fx_take_background(e->fx);
        ack(e, from, c.request_id, c.command, FT_ACK_OK, "next frame is the background");
        return;
    case FT_CMD_SEND_FULL_IMAGE:
        if (e->src.width > 65535 || e->src.height > 65535) {
            ack(e, from, c.request_id, c.command, FT_ACK_FAILED, "frame too large");
            return;
        }
        e->pending_full = 1;
        e->full_id = c.request_id;
        ack(e, from, c.request_id, c.command, FT_ACK_OK, "next frame follows as IMAGE");
        return;
    case FT_CMD_SEND_REGIONS:
        if (c.value < 0 || c.value > 255 || c.value != floor(c.value)) {
            ack(e, from, c.request_id, c.command, FT_ACK_BAD_VALUE, "half-size must be 0..255");
            return;
        }
        e->region_half = (int)c.value;
        snprintf(msg, sizeof msg, "regions half-size %d", e->region_half);
        ack(e, from, c.request_id, c.command, FT_ACK_OK, msg);
        return;
    case FT_CMD_START:
        e->state = FT_STATE_RUNNING;
        ack(e, from, c.request_id, c.command, FT_ACK_OK, "running");
        return;
    case FT_CMD_STOP:
        e->state = FT_STATE_STOPPED;
        ack(e, from, c.request_id, c.command, FT_ACK_OK, "stopped");
        return;
    default:
        ack(e, from, c.request_id, c.command, FT_ACK_UNKNOWN_COMMAND, "unknown command");
    }
}

static void poll_control(edge *e) {
    uint8_t buf[2048];
    for (;;) {
        struct sockaddr_in from;
        socklen_t fl = sizeof from;
        ssize_t n = recvfrom(e->sock, buf, sizeof buf, MSG_DONTWAIT, (struct sockaddr *)&from, &fl);
        if (n < 0)
            return; /* EAGAIN: nothing more; ICMP errors from earlier sends land here too */
        if (fl < sizeof from || from.sin_family != AF_INET ||
            !edge_config_control_allowed(&e->cfg, from.sin_addr.s_addr)) {
            if (e->control_rejected++ == 0) { /* said once; the count is logged at exit */
                char text[96];
                snprintf(text, sizeof text, "CONTROL from %s dropped: not in --control-allow",
                         inet_ntoa(from.sin_addr));
                edge_log("%s (further ones are only counted)", text);
                set_error(e, 21, text);
            } else if (e->cfg.verbose) {
                edge_log("CONTROL from %s dropped", inet_ntoa(from.sin_addr));
            }
            continue;
        }
        handle_control(e, buf, (size_t)n, &from);
    }
}

static void send_regions(edge *e, const ft_frame *f, const ft_fx_result *r) {
    int hs = e->region_half;
    for (uint32_t i = 0; i < r->n_points && i < FT_FEATURES_MAX_POINTS; i++) {
        int px = (int)r->points[i].peak_x, py = (int)r->points[i].peak_y;
        int x0 = px - hs < 0 ? 0 : px - hs, y0 = py - hs < 0 ? 0 : py - hs;
        int x1 = px + hs >= (int)e->src.width ? (int)e->src.width - 1 : px + hs;
        int y1 = py + hs >= (int)e->src.height ? (int)e->src.height - 1 : py + hs;
        send_image(e, f, FT_IMAGE_REGION, e->region_id++, (uint16_t)x0, (uint16_t)y0,
                   (uint16_t)(x1 - x0 + 1), (uint16_t)(y1 - y0 + 1));
    }
}

static void stats_tick(edge *e, uint64_t now) {
    double dt = (double)(now - e->win_start_ns) / 1e9;
    if (dt >= 1.0) {
        e->fps = (float)(e->win_frames / dt);
        e->proc_mean = e->win_frames ? (float)(e->win_proc_us_sum / e->win_frames) : 0.0f;
        e->proc_max = (float)e->win_proc_us_max;
        e->win_start_ns = now;
        e->win_frames = 0;
        e->win_proc_us_sum = e->win_proc_us_max = 0;
    }
}

static int open_socket(edge *e) {
    e->sock = socket(AF_INET, SOCK_DGRAM, 0);
    if (e->sock < 0) {
        edge_log("socket: %s", strerror(errno));
        return -1;
    }
    struct sockaddr_in a;
    memset(&a, 0, sizeof a);
    a.sin_family = AF_INET;
    a.sin_port = htons((uint16_t)e->cfg.control_port);
    if (inet_pton(AF_INET, e->cfg.bind, &a.sin_addr) != 1) {
        edge_log("--bind %s is not an IPv4 address", e->cfg.bind);
        return -1;
    }
    if (bind(e->sock, (struct sockaddr *)&a, sizeof a) < 0) {
        edge_log("cannot bind %s:%d for CONTROL: %s", e->cfg.bind, e->cfg.control_port,
                 strerror(errno));
        return -1;
    }
    memset(&e->host, 0, sizeof e->host);
    e->host.sin_family = AF_INET;
    e->host.sin_port = htons((uint16_t)e->cfg.port);
    if (inet_pton(AF_INET, e->cfg.host, &e->host.sin_addr) != 1) {
        edge_log("--host %s is not an IPv4 address", e->cfg.host);
        return -1;
    }
    edge_config_default_control(&e->cfg, e->host.sin_addr.s_addr);
    int sz = 4 << 20;
    setsockopt(e->sock, SOL_SOCKET, SO_SNDBUF, &sz, sizeof sz);
    return 0;
}

static int open_source(edge *e) {
    ft_source_req req = {e->cfg.width, e->cfg.height, e->cfg.pixel_format, e->cfg.fps,
                         e->cfg.vanish_timeout_ms};
    const char *k = e->cfg.source;
    int rc;
    if (!strcmp(k, "raw"))
        rc = ft_source_open_raw(&e->src, e->cfg.input, &req);
    else if (!strcmp(k, "y4m"))
        rc = ft_source_open_y4m(&e->src, e->cfg.input, &req);
    else if (!strcmp(k, "v4l2"))
        rc = ft_source_open_v4l2(&e->src, e->cfg.input, &req, NULL);
    else
        rc = ft_source_open_aravis(&e->src, e->cfg.input, &req);
    if (rc)
        edge_log("source %s %s: %s", k, e->cfg.input, e->src.error);
    return rc;
}

static int open_extractor(edge *e) {
    ft_fx_params p = e->cfg.fx;
    p.width = e->src.width;
    p.height = e->src.height;
    p.stride = e->src.stride;
    p.pixel_format = e->src.pixel_format;
    if (e->cfg.have_intrinsics) {
        p.fx = e->cfg.intrinsics[0];
        p.fy = e->cfg.intrinsics[1];
        p.cx = e->cfg.intrinsics[2];
        p.cy = e->cfg.intrinsics[3];
        p.skew = e->cfg.intrinsics[4];
        p.k1 = e->cfg.distortion[0];
        p.k2 = e->cfg.distortion[1];
        p.p1 = e->cfg.distortion[2];
        p.p2 = e->cfg.distortion[3];
        p.k3 = e->cfg.distortion[4];
    }
    char msg[128];
    int rc = ft_fx_params_check(&p, msg, sizeof msg);
    if (rc) {
        edge_log("bad extractor parameters: %s", msg);
        return -1;
    }
    rc = ft_fx_create(&p, sizeof p, &e->fx);
    if (rc) {
        edge_log("cannot create the extractor: %s", ft_fx_strerror(rc));
        return -1;
    }
    if (e->cfg.mask[0]) {
        size_t n = (size_t)p.width * p.height;
        uint8_t *m = malloc(n);
        FILE *f = fopen(e->cfg.mask, "rb");
        size_t got = (m && f) ? fread(m, 1, n, f) : 0;
        int extra = f ? fgetc(f) != EOF : 0;
        if (f)
            fclose(f);
        if (!m || got != n || extra) {
            edge_log("mask %s must be exactly %ux%u = %zu bytes", e->cfg.mask, p.width, p.height,
                     n);
            free(m);
            ft_fx_destroy(e->fx);
            e->fx = NULL;
            return -1;
        }
        ft_fx_set_mask(e->fx, m);
        free(m);
    }
    return 0;
}

int main(int argc, char **argv) {
    static edge e;
    int rc = edge_config_load(&e.cfg, argc, argv);
    if (rc)
        return rc > 0 ? 0 : 2;
    if (edge_is_event_source(e.cfg.source)) /* events, not frames: edge_dvs.c */
        return edge_dvs_run(&e.cfg, &ft_usb_libusb_ops);
    signal(SIGPIPE, SIG_IGN);
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    sigaction(SIGINT, &sa, NULL);
    sigaction(SIGTERM, &sa, NULL);
    if (open_socket(&e))
        return 2;
    if (open_source(&e))
        return 3;
    if (open_extractor(&e)) {
        e.src.close(&e.src);
        return 2;
    }
    e.state = e.cfg.start_stopped ? FT_STATE_IDLE : FT_STATE_RUNNING;
    e.region_half = e.cfg.region_half;
    edge_log("%s %s: %ux%u %s -> %s:%d, control on port %d", e.cfg.source, e.cfg.input, e.src.width,
             e.src.height,
             e.src.pixel_format == 0   ? "mono8"
             : e.src.pixel_format == 1 ? "mono16"
                                       : "yuyv",
             e.cfg.host, e.cfg.port, e.cfg.control_port);
    e.win_start_ns = edge_mono_ns();
    send_status(&e);
    e.last_status_ns = edge_mono_ns();
    int exit_code = 0;
    uint64_t processed = 0;
    while (!g_stop) {
        ft_frame f;
        int r = e.src.next(&e.src, &f, POLL_MS);
        if (r == FT_SRC_FRAME) {
            e.frames_seen++;
            if (e.state == FT_STATE_RUNNING) {
                uint64_t t0 = edge_mono_ns();
                ft_fx_result res;
                int prc = ft_fx_process(e.fx, f.data, f.bytes, &res);
                double us = (double)(edge_mono_ns() - t0) / 1000.0;
                if (prc) {
                    e.frames_dropped++;
                    set_error(&e, 30, ft_fx_strerror(prc));
                    edge_log("frame %llu: %s", (unsigned long long)f.camera_frame,
                             ft_fx_strerror(prc));
                } else {
                    send_features(&e, &f, &res);
                    if (e.region_half)
                        send_regions(&e, &f, &res);
                    if (res.flags & FT_FX_RES_CAND_OVERFLOW)
                        set_error(&e, 31, "too many candidate pixels: frame partly examined");
                }
                e.win_frames++;
                e.win_proc_us_sum += us;
                if (us > e.win_proc_us_max)
                    e.win_proc_us_max = us;
            }
            if (e.pending_full) {
                e.pending_full = 0;
                send_image(&e, &f, FT_IMAGE_FULL_FRAME, e.full_id, 0, 0, (uint16_t)e.src.width,
                           (uint16_t)e.src.height);
            }
            e.src.release(&e.src);
            processed++;
            if (e.cfg.max_frames && processed >= e.cfg.max_frames)
                break;
        } else if (r == FT_SRC_END) {
            edge_log("source ended after %llu frames", (unsigned long long)e.frames_seen);
            break;
        } else if (r == FT_SRC_ERROR) {
            edge_log("source failed after %llu frames: %s", (unsigned long long)e.frames_seen,
                     e.src.error);
            e.state = FT_STATE_ERROR;
            set_error(&e, 40, e.src.error);
            exit_code = 3;
            break;
        }
        poll_control(&e);
        uint64_t now = edge_mono_ns();
        stats_tick(&e, now);
        if (now - e.last_status_ns >= (uint64_t)e.cfg.status_interval_ms * 1000000ull) {
            send_status(&e);
            e.last_status_ns = now;
        }
    }
    if (e.state != FT_STATE_ERROR)
        e.state = FT_STATE_STOPPED;
    poll_control(&e);
    if (e.control_rejected)
        edge_log("dropped %llu CONTROL datagrams from senders not in --control-allow",
                 (unsigned long long)e.control_rejected);
    send_status(&e); /* the last word: why we stopped */
    e.src.close(&e.src);
    ft_fx_destroy(e.fx);
    close(e.sock);
    return exit_code;
}
