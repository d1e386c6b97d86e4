/* V4L2 source through its seam: a fake driver (no camera exists on the build machine) that plays
 * recorded buffers (synthetic frames with a blob) with sequence numbers and timestamps, and fails
 * the ways real drivers do (size adjusted, format refused, device unplugged). Run under ASan +
 * UBSan. */
#include <errno.h>
#include <linux/videodev2.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>

#include "flytrack/features.h"
#include "source.h"

#include "check.h" /* CHECK(), ft_test_failures: protocol/tests/check.h */

#define FW 64
#define FH 48
#define NREC 6

/* The fake driver's state. */
static struct {
    uint32_t max_w, max_h, fourcc_ok; /* what the "hardware" supports */
    uint32_t w, h, fourcc;
    uint8_t rec[NREC][FW * FH * 2]; /* recorded frames */
    uint8_t buf[4][FW * FH * 2];    /* the driver's mmap buffers */
    int queued[4];
    unsigned next_rec;
    uint32_t seq_step; /* 2 = every other frame lost */
    int unplug_after;  /* DQBUF fails with ENODEV after this many frames (-1 never) */
    int streaming;
} drv;

static int f_open(const char *p, int fl) {
    (void)fl;
    if (strcmp(p, "/dev/fake0")) {
        errno = ENOENT;
        return -1;
    }
    return 42;
}
static int f_close(int fd) {
    return fd == 42 ? 0 : -1;
}
static int f_poll(struct pollfd *p, nfds_t n, int t) {
    (void)n;
    (void)t;
    p->revents = POLLIN;
    return 1;
}
static void *f_mmap(void *a, size_t len, int prot, int fl, int fd, off_t off) {
    (void)a;
    (void)prot;
    (void)fl;
    (void)fd;
    if (off < 0 || off >= 4 || len > sizeof drv.buf[0])
        return MAP_FAILED;
    return drv.buf[off];
}
static int f_munmap(void *a, size_t len) {
    (void)a;
    (void)len;
    return 0;
}
static int f_ioctl(int fd, unsigned long req, void *arg) {
    (void)fd;
    uint32_t bpp = drv.fourcc == V4L2_PIX_FMT_GREY ? 1 : 2;
    switch (req) {
    case VIDIOC_QUERYCAP: {
        struct v4l2_capability *c = arg;
        c->capabilities = V4L2_CAP_VIDEO_CAPTURE | V4L2_CAP_STREAMING;
        return 0;
    }
    case VIDIOC_G_FMT:
    case VIDIOC_S_FMT: {
        struct v4l2_format *f = arg;
        if (req == VIDIOC_S_FMT) { /* like drivers: adjust to what the hardware can */
            drv.w = f->fmt.pix.width > drv.max_w ? drv.max_w : f->fmt.pix.width;
            drv.h = f->fmt.pix.height > drv.max_h ? drv.max_h : f->fmt.pix.height;
            drv.fourcc =
                f->fmt.pix.pixelformat == drv.fourcc_ok ? drv.fourcc_ok : V4L2_PIX_FMT_MJPEG;
        }
        f->fmt.pix.width = drv.w;
        f->fmt.pix.height = drv.h;
        f->fmt.pix.pixelformat = drv.fourcc;
        f->fmt.pix.bytesperline = drv.w * (drv.fourcc == V4L2_PIX_FMT_GREY ? 1 : 2);
        return 0;
    }
    case VIDIOC_REQBUFS:
        ((struct v4l2_requestbuffers *)arg)->count = 4;
        return 0;
    case VIDIOC_QUERYBUF: {
        struct v4l2_buffer *b = arg;
        b->length = drv.w * drv.h * bpp;
        b->m.offset = b->index;
        return 0;
    }
    case VIDIOC_QBUF:
        drv.queued[((struct v4l2_buffer *)arg)->index] = 1;
        return 0;
    case VIDIOC_STREAMON:
        drv.streaming = 1;
        return 0;
    case VIDIOC_STREAMOFF:
        drv.streaming = 0;
        return 0;
    case VIDIOC_DQBUF: {
        struct v4l2_buffer *b = arg;
        if (drv.unplug_after >= 0 && (int)drv.next_rec >= drv.unplug_after) {
            errno = ENODEV;
            return -1;
        }
        int i = 0;
        while (i < 4 && !drv.queued[i])
            i++;
        if (i == 4 || drv.next_rec >= NREC) {
            errno = EAGAIN;
            return -1;
        }
        drv.queued[i] = 0;
        memcpy(drv.buf[i], drv.rec[drv.next_rec], drv.w * drv.h * bpp);
        b->index = (uint32_t)i;
        b->bytesused = drv.w * drv.h * bpp;
        b->sequence = 100 + drv.next_rec * drv.seq_step;
        b->timestamp.tv_sec = 1000 + drv.next_rec;
        b->timestamp.tv_usec = 250;
        drv.next_rec++;
        return 0;
    }
    }
    errno = ENOTTY;
    return -1;
}
static const ft_v4l2_ops fake_ops = {f_open, f_close, f_ioctl, f_mmap, f_munmap, f_poll};

static void reset(uint32_t fourcc) {
    memset(&drv, 0, sizeof drv);
    drv.max_w = FW;
    drv.max_h = FH;
    drv.fourcc_ok = fourcc;
    drv.fourcc = fourcc;
    drv.w = FW;
    drv.h = FH;
    drv.seq_step = 1;
    drv.unplug_after = -1;
    int bpp = fourcc == V4L2_PIX_FMT_GREY ? 1 : 2;
    for (int k = 0; k < NREC; k++)
        for (int y = 0; y < FH; y++)
            for (int x = 0; x < FW; x++) {
                double v = 20;
                if (k > 0) /* a blob moving right by one pixel a frame */
                    v += 180 *
                         exp(-((x - 20.25 - k) * (x - 20.25 - k) + (y - 24.5) * (y - 24.5)) / 4.5);
                uint8_t *p = &drv.rec[k][(y * FW + x) * bpp];
                p[0] = (uint8_t)lround(v);
                if (bpp == 2)
                    p[1] = fourcc == V4L2_PIX_FMT_YUYV ? 128 : 0; /* Y16 here: the low byte only */
            }
}

static void play(uint32_t fourcc, int fmt) {
    reset(fourcc);
    ft_source s;
    ft_source_req req = {FW, FH, fmt, 0, 0};
    CHECK(ft_source_open_v4l2(&s, "/dev/fake0", &req, &fake_ops) == 0);
    CHECK(drv.streaming);
    ft_fx_params p;
    ft_fx_params_default(&p, s.width, s.height, s.pixel_format);
    p.stride = s.stride;
    ft_fx *fx;
    CHECK(ft_fx_create(&p, sizeof p, &fx) == 0);
    int frames = 0;
    for (;;) {
        ft_frame f;
        int r = s.next(&s, &f, 10);
        if (r != FT_SRC_FRAME)
            break;
        CHECK(f.camera_frame == 100u + (unsigned)frames);
        CHECK(f.device_timestamp_ns == (1000ull + (unsigned)frames) * 1000000000ull + 250000ull);
        ft_fx_result res;
        CHECK(ft_fx_process(fx, f.data, f.bytes, &res) == 0);
        if (frames > 0) {
            CHECK(res.n_points == 1);
            if (res.n_points == 1)
                CHECK(fabs(res.points[0].x_dist - (20.25 + frames)) < 0.06 &&
                      fabs(res.points[0].y_dist - 24.5) < 0.06);
        }
        s.release(&s);
        frames++;
    }
    CHECK(frames == NREC);
    s.close(&s);
    CHECK(!drv.streaming);
    ft_fx_destroy(fx);
}

int main(void) {
    play(V4L2_PIX_FMT_GREY, FT_FX_MONO8);
    play(V4L2_PIX_FMT_Y16, FT_FX_MONO16);
    play(V4L2_PIX_FMT_YUYV, FT_FX_YUYV);

    ft_source s;
    ft_source_req req = {FW, FH, FT_FX_MONO8, 0, 0};
    /* Wrong frame size: the driver adjusts 640x480 down to what it has. */
    reset(V4L2_PIX_FMT_GREY);
    ft_source_req big = {640, 480, FT_FX_MONO8, 0, 0};
    CHECK(ft_source_open_v4l2(&s, "/dev/fake0", &big, &fake_ops) == -1);
    CHECK(strstr(s.error, "cannot do 640x480") != NULL);
    /* Pixel format the camera does not have. */
    reset(V4L2_PIX_FMT_YUYV);
    CHECK(ft_source_open_v4l2(&s, "/dev/fake0", &req, &fake_ops) == -1);
    CHECK(strstr(s.error, "does not do pixel format GREY") != NULL);
    /* No such device. */
    CHECK(ft_source_open_v4l2(&s, "/dev/nothing", &req, &fake_ops) == -1);
    CHECK(strstr(s.error, "cannot open /dev/nothing") != NULL);
    /* Lost frames are counted from sequence gaps; unplugging is an error, not a crash. */
    reset(V4L2_PIX_FMT_GREY);
    drv.seq_step = 2;
    drv.unplug_after = 3;
    CHECK(ft_source_open_v4l2(&s, "/dev/fake0", &req, &fake_ops) == 0);
    ft_frame f;
    int n = 0, r;
    while ((r = s.next(&s, &f, 10)) == FT_SRC_FRAME) {
        s.release(&s);
        n++;
    }
    CHECK(n == 3 && r == FT_SRC_ERROR && s.dropped == 2);
    CHECK(strstr(s.error, "camera vanished") != NULL);
    s.close(&s);
    if (ft_test_failures) {
        fprintf(stderr, "%d check(s) failed\n", ft_test_failures);
        return 1;
    }
    printf("test_v4l2_seam: all checks passed\n");
    return 0;
}
