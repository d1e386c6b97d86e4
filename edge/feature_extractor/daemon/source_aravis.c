/* GenICam cameras through Aravis 0.8 (GigE Vision and USB3 Vision). Tested against Aravis's own
 * fake GigE camera (arv-fake-gv-camera-0.8) on loopback; the camera is named as Aravis lists it
 * ("Aravis-Fake-<serial>", "<vendor>-<serial>") or by its IP address. */
#include <arpa/inet.h>
#include <arv.h>
#include <netinet/in.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "flytrack/features.h"
#include "source.h"

#include <sys/socket.h>
#include <unistd.h>

#define N_BUFFERS 8

typedef struct {
    ArvCamera *cam;
    ArvStream *stream;
    ArvBuffer *held;
    size_t frame_bytes;
    uint64_t last_frame_ns;
    int vanish_ms;
    guint64 last_id;
    int have_id;
} arv_priv;

__attribute__((format(printf, 2, 3))) static int aerr(ft_source *s, const char *fmt, ...) {
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(s->error, sizeof s->error, fmt, ap);
    va_end(ap);
    return -1;
}

static int arv_next(ft_source *s, ft_frame *f, int timeout_ms) {
    arv_priv *a = s->priv;
    ArvBuffer *b = arv_stream_timeout_pop_buffer(a->stream, (guint64)timeout_ms * 1000u);
    uint64_t now = ft_now_ns();
    if (!b) {
        if (a->vanish_ms > 0 && now - a->last_frame_ns > (uint64_t)a->vanish_ms * 1000000ull) {
            aerr(s, "camera vanished: no frame for %d ms", a->vanish_ms);
            return FT_SRC_ERROR;
        }
        return FT_SRC_TIMEOUT;
    }
    a->last_frame_ns = now;
    size_t size = 0;
    const void *data = arv_buffer_get_data(b, &size);
    guint64 id = arv_buffer_get_frame_id(b);
    if (a->have_id && id > a->last_id + 1)
        s->dropped += id - a->last_id - 1;
    a->last_id = id;
    a->have_id = 1;
    if (arv_buffer_get_status(b) != ARV_BUFFER_STATUS_SUCCESS || size < a->frame_bytes) {
        s->dropped++;
        arv_stream_push_buffer(a->stream, b);
        return FT_SRC_TIMEOUT;
    }
    a->held = b;
    f->recv_ns = now;
    f->data = data;
    f->bytes = size;
    f->camera_frame = id;
    f->device_timestamp_ns = arv_buffer_get_timestamp(b);
    return FT_SRC_FRAME;
}

static void arv_release(ft_source *s) {
    arv_priv *a = s->priv;
    if (a->held) {
        arv_stream_push_buffer(a->stream, a->held);
        a->held = NULL;
    }
}

static void arv_close(ft_source *s) {
    arv_priv *a = s->priv;
    if (!a)
        return;
    if (a->cam)
        arv_camera_stop_acquisition(a->cam, NULL);
    if (a->held)
        g_object_unref(a->held);
    if (a->stream)
        g_object_unref(a->stream);
    if (a->cam)
        g_object_unref(a->cam);
    free(a);
    s->priv = NULL;
    arv_shutdown();
}

/* The local address the kernel sends from to reach `dev`; the camera's stream packets come back to
 * it. Returns 0 or -1. */
static int route_source(GInetAddress *dev, struct in_addr *out) {
    if (g_inet_address_get_family(dev) != G_SOCKET_FAMILY_IPV4)
        return -1;
    struct sockaddr_in to = {.sin_family = AF_INET, .sin_port = htons(3956)}; /* GVCP port */
    memcpy(&to.sin_addr, g_inet_address_to_bytes(dev), 4);
    int fd = socket(AF_INET, SOCK_DGRAM, 0);
    if (fd < 0)
        return -1;
    struct sockaddr_in me;
    socklen_t len = sizeof me;
    int rc = connect(fd, (struct sockaddr *)&to, sizeof to) == 0 &&
                     getsockname(fd, (struct sockaddr *)&me, &len) == 0
                 ? 0
                 : -1;
    close(fd);
    if (rc == 0)
        *out = me.sin_addr;
    return rc;
}

/* A GigE camera found by name is bound to the host interface whose discovery socket got its answer,
 * and Aravis sets the stream destination (GevSCDA) to that interface's address and receives with a
 * packet socket (AF_PACKET) on that interface. When the camera lives on this host (Aravis's fake
 * camera on 127.0.0.1, answering broadcasts on every interface), discovery can answer through eth0:
 * the camera then streams to eth0's address, the kernel delivers that through `lo`, and the packet
 * socket on eth0 never sees a frame (issue 4; `arv-camera-test-0.8 -n NAME` shows the same: 0
 * packets). So: when the kernel's route to the camera leaves from another local address than the
 * one discovery chose, reopen the device with that address as the host interface, as opening by
 * address does. On a real rig the two agree and the camera is used as opened. */
static ArvCamera *rebind_to_route(ArvCamera *cam, const char *camera) {
    if (!arv_camera_is_gv_device(cam))
        return cam;
    ArvGvDevice *gv = ARV_GV_DEVICE(arv_camera_get_device(cam));
    GInetAddress *dev = g_inet_socket_address_get_address(
        G_INET_SOCKET_ADDRESS(arv_gv_device_get_device_address(gv)));
    GInetAddress *itf = g_inet_socket_address_get_address(
        G_INET_SOCKET_ADDRESS(arv_gv_device_get_interface_address(gv)));
    struct in_addr route;
    if (route_source(dev, &route) != 0 || g_inet_address_get_family(itf) != G_SOCKET_FAMILY_IPV4 ||
        memcmp(g_inet_address_to_bytes(itf), &route, 4) == 0)
        return cam;
    GInetAddress *local =
        g_inet_address_new_from_bytes((const guint8 *)&route, G_SOCKET_FAMILY_IPV4);
    GInetAddress *remote = g_object_ref(dev);
    gchar *itf_s = g_inet_address_to_string(itf), *local_s = g_inet_address_to_string(local),
          *dev_s = g_inet_address_to_string(dev);
    fprintf(stderr,
            "flytrack-edge: camera %s at %s was discovered through %s, but this host reaches it "
            "from %s: reopening it there so its stream comes back to a socket that sees it\n",
            camera, dev_s, itf_s, local_s);
    g_free(itf_s);
    g_free(local_s);
    g_free(dev_s);
    g_object_unref(cam); /* leaves control of the camera before the new device takes it */
    GError *err = NULL;
    ArvCamera *out = NULL;
    ArvDevice *d = arv_gv_device_new(local, remote, &err);
    if (d) {
        out = arv_camera_new_with_device(d, &err); /* takes its own reference */
        g_object_unref(d);
    }
    if (err) {
        fprintf(stderr, "flytrack-edge: reopening camera %s: %s\n", camera, err->message);
        g_clear_error(&err);
    }
    g_object_unref(local);
    g_object_unref(remote);
    return out;
}

#define TRY(call, what)                                                                            \
    do {                                                                                           \
        GError *e_ = NULL;                                                                         \
        call;                                                                                      \
        if (e_) {                                                                                  \
            aerr(s, "camera %s: %s: %s", camera, what, e_->message);                               \
            g_clear_error(&e_);                                                                    \
            goto fail;                                                                             \
        }                                                                                          \
    } while (0)

int ft_source_open_aravis(ft_source *s, const char *camera, const ft_source_req *req) {
    memset(s, 0, sizeof *s);
    arv_priv *a = calloc(1, sizeof *a);
    if (!a)
        return aerr(s, "out of memory");
    s->priv = a;
    s->next = arv_next;
    s->release = arv_release;
    s->close = arv_close;
    a->vanish_ms = req->vanish_timeout_ms;
    GError *err = NULL;
    a->cam = arv_camera_new(camera, &err);
    if (!a->cam) {
        aerr(s, "cannot open camera %s: %s", camera, err ? err->message : "not found");
        g_clear_error(&err);
        goto fail;
    }
    a->cam = rebind_to_route(a->cam, camera);
    if (!a->cam) {
        aerr(s, "cannot open camera %s on the host address that reaches it", camera);
        goto fail;
    }
    int fmt = req->pixel_format < 0 ? FT_FX_MONO8 : req->pixel_format;
    ArvPixelFormat pf = fmt == FT_FX_MONO8    ? ARV_PIXEL_FORMAT_MONO_8
                        : fmt == FT_FX_MONO16 ? ARV_PIXEL_FORMAT_MONO_16
                                              : ARV_PIXEL_FORMAT_YUV_422_YUYV_PACKED;
    TRY(arv_camera_set_pixel_format(a->cam, pf, &e_), "setting the pixel format");
    TRY(
        ArvPixelFormat now = arv_camera_get_pixel_format(a->cam, &e_); if (!e_ && now != pf) {
            aerr(s, "camera %s does not take pixel format %d", camera, fmt);
            goto fail;
        },
                                                                       "reading the pixel format");
    gint x = 0, y = 0, w = 0, h = 0;
    if (req->width && req->height)
        TRY(arv_camera_set_region(a->cam, 0, 0, (gint)req->width, (gint)req->height, &e_),
            "setting the region");
    TRY(arv_camera_get_region(a->cam, &x, &y, &w, &h, &e_), "reading the region");
    if ((req->width && (uint32_t)w != req->width) || (req->height && (uint32_t)h != req->height)) {
        aerr(s, "camera %s gives %dx%d frames, %ux%u were asked for", camera, w, h, req->width,
             req->height);
        goto fail;
    }
    if (req->fps > 0)
        TRY(arv_camera_set_frame_rate(a->cam, req->fps, &e_), "setting the frame rate");
    TRY(arv_camera_set_acquisition_mode(a->cam, ARV_ACQUISITION_MODE_CONTINUOUS, &e_),
        "setting continuous acquisition");
    s->width = (uint32_t)w;
    s->height = (uint32_t)h;
    s->pixel_format = fmt;
    s->stride = (uint32_t)w * (fmt == FT_FX_MONO8 ? 1u : 2u);
    a->frame_bytes = (size_t)s->stride * (size_t)h;
    TRY(a->stream = arv_camera_create_stream(a->cam, NULL, NULL, &e_), "creating the stream");
    guint payload = 0;
    TRY(payload = arv_camera_get_payload(a->cam, &e_), "reading the payload size");
    for (int i = 0; i < N_BUFFERS; i++)
        arv_stream_push_buffer(a->stream, arv_buffer_new(payload, NULL));
    TRY(arv_camera_start_acquisition(a->cam, &e_), "starting acquisition");
    a->last_frame_ns = ft_now_ns();
    return 0;
fail:
    arv_close(s);
    return -1;
}
