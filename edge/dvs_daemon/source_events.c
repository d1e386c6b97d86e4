/* Event sources: files through libflytrack_events, and a DVS128 through libusb behind ft_usb_ops.
 */
#define _POSIX_C_SOURCE 200809L
#include "source_events.h"

#include <errno.h>
#include <libusb.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

static uint64_t mono_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (uint64_t)ts.tv_sec * 1000000000ull + (uint64_t)ts.tv_nsec;
}

static void sleep_ns(uint64_t ns) {
    struct timespec ts = {(time_t)(ns / 1000000000ull), (long)(ns % 1000000000ull)};
    while (nanosleep(&ts, &ts) != 0 && errno == EINTR) {
    }
}

/* ---- event files ------------------------------------------------------------------------------
 */

#define FILE_BUF 65536

typedef struct {
    ft_ev_reader *r;
    int realtime, ended, failed;
    ft_event buf[FILE_BUF];
    size_t off, len;
    int64_t t0;     /* first event time */
    uint64_t wall0; /* monotonic ns when it was delivered */
} file_priv;

static long file_next(ft_ev_source *s, ft_event *out, size_t cap, int timeout_ms) {
    file_priv *p = s->priv;
    if (p->off == p->len) {
        if (p->failed)
            return FT_SRC_ERROR;
        if (p->ended)
            return FT_SRC_END;
        if (!ft_ev_poll(p->r, timeout_ms)) /* a pipe with nothing new: back to the loop */
            return 0;
        long long n = ft_ev_read(p->r, p->buf, FILE_BUF);
        /* The frame syncs are the rising edges (or pulses) of the recorded trigger input. */
        ft_ev_trigger tt[64];
        size_t k;
        while ((k = ft_ev_triggers(p->r, tt, sizeof tt / sizeof tt[0])) > 0)
            for (size_t j = 0; j < k; j++)
                if (tt[j].value)
                    s->sync_t[s->triggers++ % FT_SRC_SYNC_RING] = tt[j].t;
        if (n < 0) { /* the events before the damage were delivered already */
            snprintf(s->error, sizeof s->error, "%.230s", ft_ev_error(p->r));
            p->failed = 1;
            return FT_SRC_ERROR;
        }
        if (n == 0) {
            p->ended = 1;
            return FT_SRC_END;
        }
        p->off = 0;
        p->len = (size_t)n;
        if (p->wall0 == 0) {
            p->t0 = p->buf[0].t;
            p->wall0 = mono_ns();
        }
    }
    size_t n = p->len - p->off < cap ? p->len - p->off : cap;
    if (p->realtime) { /* only the events whose recorded time has come */
        uint64_t now = mono_ns();
        int64_t due_us = (int64_t)((now - p->wall0) / 1000) + p->t0;
        size_t k = 0;
        while (k < n && p->buf[p->off + k].t <= due_us)
            k++;
        if (k == 0) {
            uint64_t wait = (uint64_t)(p->buf[p->off].t - due_us) * 1000ull;
            uint64_t cap_ns = (uint64_t)timeout_ms * 1000000ull;
            sleep_ns(wait < cap_ns ? wait : cap_ns);
            return 0;
        }
        n = k;
    }
    memcpy(out, p->buf + p->off, n * sizeof *out);
    p->off += n;
    s->drained = p->off == p->len;
    return (long)n;
}

static void file_close(ft_ev_source *s) {
    file_priv *p = s->priv;
    if (p) {
        ft_ev_close(p->r);
        free(p);
    }
    s->priv = NULL;
}

int ft_ev_source_open_file(ft_ev_source *s, const char *path, const char *format, int realtime) {
    memset(s, 0, sizeof *s);
    int fmt = FT_EV_AUTO;
    if (format && *format && strcmp(format, "auto") != 0) {
        fmt = ft_ev_format_from_name(format);
        if (fmt <= 0) {
            snprintf(s->error, sizeof s->error,
                     "unknown event format '%.40s' (aedat2, aedat3, aedat4, evt2, evt3, dat)",
                     format);
            return -1;
        }
    }
    file_priv *p = calloc(1, sizeof *p);
    if (!p) {
        snprintf(s->error, sizeof s->error, "out of memory");
        return -1;
    }
    /* "-": standard input, e.g. a program that produces events as they happen */
    p->r = ft_ev_open(strcmp(path, "-") ? path : "/dev/stdin", fmt, s->error, sizeof s->error);
    if (!p->r) {
        free(p);
        return -1;
    }
    ft_ev_keep_triggers(p->r, 1);
    ft_ev_info info;
    ft_ev_get_info(p->r, &info);
    p->realtime = realtime;
    s->width = (uint32_t)info.width;
    s->height = (uint32_t)info.height;
    s->connected = 1;
    s->next = file_next;
    s->close = file_close;
    s->priv = p;
    return 0;
}

/* ---- DVS128 on USB ----------------------------------------------------------------------------
 */

#define USB_BUF 16384

typedef struct {
    const ft_usb_ops *ops;
    void *ctx, *h;
    ft_dvs_stream st;
    uint8_t buf[USB_BUF];
    size_t off, len;
    uint8_t biases[FT_DVS128_BIAS_BYTES];
    int have_biases, reopen_ms;
    int pending_loss; /* the last transfer failed after delivering bytes: lost once they are used */
    uint64_t next_try_ns;
} dvs_priv;

/* Opens the device and starts it: biases (if given), timestamp master, reset timestamps, start. */
static int dvs_start(ft_ev_source *s, dvs_priv *p) {
    p->h = p->ops->open(p->ctx, FT_DVS128_VID, FT_DVS128_PID);
    if (!p->h)
        return -1;
    int rc = FT_USB_OK;
    if (p->have_biases)
        rc = p->ops->control_out(p->h, FT_DVS128_REQ_BIASES, 0, p->biases, FT_DVS128_BIAS_BYTES,
                                 1000);
    if (rc == FT_USB_OK)
        rc = p->ops->control_out(p->h, FT_DVS128_REQ_TS_MASTER, 1, NULL, 0, 1000);
    if (rc == FT_USB_OK)
        rc = p->ops->control_out(p->h, FT_DVS128_REQ_RESET_TS, 0, NULL, 0, 1000);
    if (rc == FT_USB_OK)
        rc = p->ops->control_out(p->h, FT_DVS128_REQ_START, 0, NULL, 0, 1000);
    if (rc != FT_USB_OK) {
        snprintf(s->error, sizeof s->error, "DVS128 did not take its start requests (error %d)",
                 rc);
        p->ops->close(p->h);
        p->h = NULL;
        return -1;
    }
    /* the device's time base restarts at 0: so does the decoder, and a half word is dropped */
    ft_dvs_stream_restart(&p->st);
    p->off = p->len = 0;
    return 0;
}

static void dvs_lost(ft_ev_source *s, dvs_priv *p, int rc) {
    p->ops->close(p->h);
    p->h = NULL;
    s->connected = 0;
    s->state_changed = 1;
    p->next_try_ns = mono_ns() + (uint64_t)p->reopen_ms * 1000000ull;
    snprintf(s->error, sizeof s->error, "DVS128 %s (error %d); reopening every %d ms",
             rc == FT_USB_NO_DEVICE ? "unplugged" : "transfer failed", rc, p->reopen_ms);
}

static long dvs_next(ft_ev_source *s, ft_event *out, size_t cap, int timeout_ms) {
    dvs_priv *p = s->priv;
    if (!p->h) { /* unplugged: try again every reopen_ms */
        uint64_t now = mono_ns();
        if (now < p->next_try_ns) {
            uint64_t wait = p->next_try_ns - now, cap_ns = (uint64_t)timeout_ms * 1000000ull;
            sleep_ns(wait < cap_ns ? wait : cap_ns);
            return 0;
        }
        if (dvs_start(s, p) != 0) {
            p->next_try_ns = now + (uint64_t)p->reopen_ms * 1000000ull;
            return 0;
        }
        s->connected = 1;
        s->state_changed = 1;
        s->reconnects++;
    }
    if (p->off == p->len) {
        if (p->pending_loss) { /* the bytes that came with the failing transfer are decoded */
            dvs_lost(s, p, p->pending_loss);
            p->pending_loss = 0;
            return 0;
        }
        int got = 0;
        int rc = p->ops->bulk_in(p->h, FT_DVS128_EP_IN, p->buf, USB_BUF, &got,
                                 (unsigned)(timeout_ms > 0 ? timeout_ms : 1));
        if (rc != FT_USB_OK && rc != FT_USB_TIMEOUT) {
            if (got <= 0) {
                dvs_lost(s, p, rc);
                return 0;
            }
            p->pending_loss = rc;
        }
        p->off = 0;
        p->len = got > 0 ? (size_t)got : 0;
        if (!p->len)
            return 0;
    }
    size_t used;
    size_t n = ft_dvs_stream_feed(&p->st, p->buf + p->off, p->len - p->off, out, cap, &used);
    p->off += used;
    if (s->invert_polarity)
        for (size_t i = 0; i < n; i++)
            out[i].p ^= 1u;
    s->lost = p->st.bad_words;
    for (uint64_t i = s->triggers; i < p->st.syncs; i++)
        s->sync_t[i % FT_SRC_SYNC_RING] = p->st.sync_t[i % FT_DVS_STREAM_SYNCS];
    s->triggers = p->st.syncs;
    s->drained = p->off == p->len;
    return (long)n;
}

static void dvs_close(ft_ev_source *s) {
    dvs_priv *p = s->priv;
    if (!p)
        return;
    if (p->h) {
        p->ops->control_out(p->h, FT_DVS128_REQ_STOP, 0, NULL, 0, 1000);
        p->ops->close(p->h);
    }
    if (p->ops->exit)
        p->ops->exit(p->ctx);
    free(p);
    s->priv = NULL;
}

int ft_ev_source_open_dvs128(ft_ev_source *s, const ft_usb_ops *ops, const uint8_t *biases,
                             int reopen_ms) {
    memset(s, 0, sizeof *s);
    dvs_priv *p = calloc(1, sizeof *p);
    if (!p) {
        snprintf(s->error, sizeof s->error, "out of memory");
        return -1;
    }
    p->ops = ops;
    p->reopen_ms = reopen_ms > 0 ? reopen_ms : 500;
    if (biases) {
        memcpy(p->biases, biases, FT_DVS128_BIAS_BYTES);
        p->have_biases = 1;
    }
    ft_dvs_stream_init(&p->st);
    if (ops->init && ops->init(&p->ctx) != 0) {
        snprintf(s->error, sizeof s->error, "cannot initialise libusb");
        free(p);
        return -1;
    }
    if (dvs_start(s, p) != 0) {
        if (!s->error[0])
            snprintf(s->error, sizeof s->error,
                     "no DVS128 (USB %04x:%04x) found, or no permission to open it", FT_DVS128_VID,
                     FT_DVS128_PID);
        if (ops->exit)
            ops->exit(p->ctx);
        free(p);
        return -1;
    }
    s->width = s->height = 128;
    s->connected = 1;
    s->next = dvs_next;
    s->close = dvs_close;
    s->priv = p;
    return 0;
}

/* ---- the real USB layer: libusb-1.0 (not reachable in tests: no device here) ------------------
 */

static int lu_init(void **ctx) {
    libusb_context *c = NULL;
    if (libusb_init(&c) != 0)
        return -1;
    *ctx = c;
    return 0;
}

static void lu_exit(void *ctx) {
    libusb_exit(ctx);
}

static void *lu_open(void *ctx, uint16_t vid, uint16_t pid) {
    libusb_device_handle *h = libusb_open_device_with_vid_pid(ctx, vid, pid);
    if (!h)
        return NULL;
    libusb_set_auto_detach_kernel_driver(h, 1);
    if (libusb_claim_interface(h, 0) != 0) {
        libusb_close(h);
        return NULL;
    }
    return h;
}

static int lu_map(int rc) {
    if (rc >= 0)
        return FT_USB_OK;
    if (rc == LIBUSB_ERROR_TIMEOUT)
        return FT_USB_TIMEOUT;
    if (rc == LIBUSB_ERROR_NO_DEVICE || rc == LIBUSB_ERROR_IO || rc == LIBUSB_ERROR_PIPE)
        return FT_USB_NO_DEVICE;
    return FT_USB_ERROR;
}

static int lu_control_out(void *h, uint8_t request, uint16_t value, const uint8_t *data,
                          uint16_t len, unsigned timeout_ms) {
    int rc = libusb_control_transfer(
        h, LIBUSB_ENDPOINT_OUT | LIBUSB_REQUEST_TYPE_VENDOR | LIBUSB_RECIPIENT_DEVICE, request,
        value, 0, (unsigned char *)(uintptr_t)data, len, timeout_ms);
    return lu_map(rc);
}

static int lu_bulk_in(void *h, uint8_t ep, uint8_t *buf, int len, int *got, unsigned timeout_ms) {
    *got = 0;
    return lu_map(libusb_bulk_transfer(h, ep, buf, len, got, timeout_ms));
}

static void lu_close(void *h) {
    libusb_release_interface(h, 0);
    libusb_close(h);
}

const ft_usb_ops ft_usb_libusb_ops = {lu_init,        lu_exit,    lu_open,
                                      lu_control_out, lu_bulk_in, lu_close};
