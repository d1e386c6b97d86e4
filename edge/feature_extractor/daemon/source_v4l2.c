/* V4L2 capture: mmap streaming, GREY / Y16 / YUYV, driver timestamps and sequence numbers.
 *
 * Every kernel call goes through an ft_v4l2_ops seam (source.h). The build machine has no camera,
 * so tests/test_v4l2_seam.c drives this file with a fake driver playing recorded buffers; in
 * production ft_v4l2_sys_ops calls the kernel.
 */
#include <errno.h>
#include <fcntl.h>
#include <linux/videodev2.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/ioctl.h>
#include <sys/mman.h>
#include <unistd.h>

#include "flytrack/features.h"
#include "source.h"

#define N_BUFFERS 4

static int sys_open(const char *path, int flags) {
    return open(path, flags);
}
static int sys_ioctl(int fd, unsigned long req, void *arg) {
    return ioctl(fd, req, arg);
}
const ft_v4l2_ops ft_v4l2_sys_ops = {sys_open, close, sys_ioctl, mmap, munmap, poll};

typedef struct {
    const ft_v4l2_ops *ops;
    int fd;
    void *mem[N_BUFFERS];
    size_t len[N_BUFFERS];
    unsigned n_buf;
    int held; /* index of the buffer the caller holds, -1 none */
    int streaming;
    size_t frame_bytes;
    uint32_t last_seq;
    int have_seq;
} v4l2_priv;

__attribute__((format(printf, 2, 3))) static int verr(ft_source *s, const char *fmt, ...) {
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(s->error, sizeof s->error, fmt, ap);
    va_end(ap);
    return -1;
}

static int xioctl(v4l2_priv *v, unsigned long req, void *arg) {
    int r;
    do
        r = v->ops->ioctl(v->fd, req, arg);
    while (r < 0 && errno == EINTR);
    return r;
}

static int v4l2_next(ft_source *s, ft_frame *f, int timeout_ms) {
    v4l2_priv *v = s->priv;
    struct pollfd p = {.fd = v->fd, .events = POLLIN};
    int r = v->ops->poll(&p, 1, timeout_ms);
    if (r < 0)
        return errno == EINTR ? FT_SRC_TIMEOUT
                              : (verr(s, "poll: %s", strerror(errno)), FT_SRC_ERROR);
    if (r == 0)
        return FT_SRC_TIMEOUT;
    if (p.revents & (POLLERR | POLLHUP | POLLNVAL)) {
        verr(s, "camera vanished (poll reports an error on the device)");
        return FT_SRC_ERROR;
    }
    struct v4l2_buffer b;
    memset(&b, 0, sizeof b);
    b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    b.memory = V4L2_MEMORY_MMAP;
    if (xioctl(v, VIDIOC_DQBUF, &b) < 0) {
        if (errno == EAGAIN)
            return FT_SRC_TIMEOUT;
        verr(s, "camera vanished: VIDIOC_DQBUF: %s", strerror(errno));
        return FT_SRC_ERROR;
    }
    if (b.index >= v->n_buf) {
        verr(s, "driver returned buffer %u of %u", b.index, v->n_buf);
        return FT_SRC_ERROR;
    }
    f->recv_ns = ft_now_ns();
    if (v->have_seq && b.sequence > v->last_seq + 1)
        s->dropped += b.sequence - v->last_seq - 1;
    v->last_seq = b.sequence;
    v->have_seq = 1;
    if ((b.flags & V4L2_BUF_FLAG_ERROR) || b.bytesused < v->frame_bytes) {
        /* a damaged or short frame: count it and give the buffer back */
        s->dropped++;
        xioctl(v, VIDIOC_QBUF, &b);
        return FT_SRC_TIMEOUT;
    }
    v->held = (int)b.index;
    f->data = v->mem[b.index];
    f->bytes = b.bytesused;
    f->camera_frame = b.sequence;
    f->device_timestamp_ns =
        (uint64_t)b.timestamp.tv_sec * 1000000000ull + (uint64_t)b.timestamp.tv_usec * 1000ull;
    return FT_SRC_FRAME;
}

static void v4l2_release(ft_source *s) {
    v4l2_priv *v = s->priv;
    if (v->held < 0)
        return;
    struct v4l2_buffer b;
    memset(&b, 0, sizeof b);
    b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    b.memory = V4L2_MEMORY_MMAP;
    b.index = (unsigned)v->held;
    xioctl(v, VIDIOC_QBUF, &b);
    v->held = -1;
}

static void v4l2_close(ft_source *s) {
    v4l2_priv *v = s->priv;
    if (!v)
        return;
    if (v->streaming) {
        int type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
        xioctl(v, VIDIOC_STREAMOFF, &type);
    }
    for (unsigned i = 0; i < v->n_buf; i++)
        if (v->mem[i] && v->mem[i] != MAP_FAILED)
            v->ops->munmap(v->mem[i], v->len[i]);
    if (v->fd >= 0)
        v->ops->close(v->fd);
    free(v);
    s->priv = NULL;
}

static const char *fourcc_str(uint32_t f, char out[5]) {
    for (int i = 0; i < 4; i++) {
        char c = (char)((f >> (8 * i)) & 0xFF);
        out[i] = (c >= 32 && c < 127) ? c : '?';
    }
    out[4] = 0;
    return out;
}

int ft_source_open_v4l2(ft_source *s, const char *device, const ft_source_req *req,
                        const ft_v4l2_ops *ops) {
    memset(s, 0, sizeof *s);
    v4l2_priv *v = calloc(1, sizeof *v);
    if (!v)
        return verr(s, "out of memory");
    v->ops = ops ? ops : &ft_v4l2_sys_ops;
    v->held = -1;
    s->priv = v;
    s->next = v4l2_next;
    s->release = v4l2_release;
    s->close = v4l2_close;
    v->fd = v->ops->open(device, O_RDWR | O_NONBLOCK);
    if (v->fd < 0) {
        verr(s, "cannot open %s: %s", device, strerror(errno));
        v4l2_close(s);
        return -1;
    }
    struct v4l2_capability cap;
    memset(&cap, 0, sizeof cap);
    if (xioctl(v, VIDIOC_QUERYCAP, &cap) < 0) {
        verr(s, "%s is not a V4L2 device (VIDIOC_QUERYCAP: %s)", device, strerror(errno));
        goto fail;
    }
    uint32_t caps = (cap.capabilities & V4L2_CAP_DEVICE_CAPS) ? cap.device_caps : cap.capabilities;
    if (!(caps & V4L2_CAP_VIDEO_CAPTURE) || !(caps & V4L2_CAP_STREAMING)) {
        verr(s, "%s cannot capture video by streaming", device);
        goto fail;
    }
    int fmt = req->pixel_format < 0 ? FT_FX_MONO8 : req->pixel_format;
    uint32_t fourcc = fmt == FT_FX_MONO8    ? V4L2_PIX_FMT_GREY
                      : fmt == FT_FX_MONO16 ? V4L2_PIX_FMT_Y16
                                            : V4L2_PIX_FMT_YUYV;
    struct v4l2_format vf;
    memset(&vf, 0, sizeof vf);
    vf.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    if (xioctl(v, VIDIOC_G_FMT, &vf) < 0) {
        verr(s, "VIDIOC_G_FMT: %s", strerror(errno));
        goto fail;
    }
    if (req->width)
        vf.fmt.pix.width = req->width;
    if (req->height)
        vf.fmt.pix.height = req->height;
    vf.fmt.pix.pixelformat = fourcc;
    vf.fmt.pix.field = V4L2_FIELD_NONE;
    vf.fmt.pix.bytesperline = 0;
    if (xioctl(v, VIDIOC_S_FMT, &vf) < 0) {
        verr(s, "VIDIOC_S_FMT: %s", strerror(errno));
        goto fail;
    }
    char got[5], want[5];
    if (vf.fmt.pix.pixelformat != fourcc) {
        verr(s, "%s does not do pixel format %s (it offers %s)", device, fourcc_str(fourcc, want),
             fourcc_str(vf.fmt.pix.pixelformat, got));
        goto fail;
    }
    if ((req->width && vf.fmt.pix.width != req->width) ||
        (req->height && vf.fmt.pix.height != req->height)) {
        verr(s, "%s cannot do %ux%u (the driver offers %ux%u)", device, req->width, req->height,
             vf.fmt.pix.width, vf.fmt.pix.height);
        goto fail;
    }
    uint32_t bpp = fmt == FT_FX_MONO8 ? 1 : 2;
    s->width = vf.fmt.pix.width;
    s->height = vf.fmt.pix.height;
    s->pixel_format = fmt;
    s->stride = vf.fmt.pix.bytesperline ? vf.fmt.pix.bytesperline : s->width * bpp;
    if (s->stride < s->width * bpp) {
        verr(s, "driver's bytesperline %u is smaller than a row", s->stride);
        goto fail;
    }
    v->frame_bytes = (size_t)s->stride * (s->height - 1) + (size_t)s->width * bpp;
    struct v4l2_requestbuffers rb;
    memset(&rb, 0, sizeof rb);
    rb.count = N_BUFFERS;
    rb.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    rb.memory = V4L2_MEMORY_MMAP;
    if (xioctl(v, VIDIOC_REQBUFS, &rb) < 0 || rb.count < 2) {
        verr(s, "%s: cannot get mmap buffers (VIDIOC_REQBUFS)", device);
        goto fail;
    }
    v->n_buf = rb.count > N_BUFFERS ? N_BUFFERS : rb.count;
    for (unsigned i = 0; i < v->n_buf; i++) {
        struct v4l2_buffer b;
        memset(&b, 0, sizeof b);
        b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
        b.memory = V4L2_MEMORY_MMAP;
        b.index = i;
        if (xioctl(v, VIDIOC_QUERYBUF, &b) < 0) {
            verr(s, "VIDIOC_QUERYBUF: %s", strerror(errno));
            goto fail;
        }
        v->len[i] = b.length;
        v->mem[i] = v->ops->mmap(NULL, b.length, PROT_READ | PROT_WRITE, MAP_SHARED, v->fd,
                                 (off_t)b.m.offset);
        if (v->mem[i] == MAP_FAILED) {
            verr(s, "mmap of buffer %u: %s", i, strerror(errno));
            goto fail;
        }
        if (xioctl(v, VIDIOC_QBUF, &b) < 0) {
            verr(s, "VIDIOC_QBUF: %s", strerror(errno));
            goto fail;
        }
    }
    int type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    if (xioctl(v, VIDIOC_STREAMON, &type) < 0) {
        verr(s, "VIDIOC_STREAMON: %s", strerror(errno));
        goto fail;
    }
    v->streaming = 1;
    return 0;
fail:
    v4l2_close(s);
    return -1;
}
