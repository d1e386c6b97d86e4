/* Frame sources of flytrack-edge behind one interface: raw / Y4M files and pipes, V4L2, Aravis. */
#ifndef FLYTRACK_EDGE_SOURCE_H
#define FLYTRACK_EDGE_SOURCE_H

#include <poll.h>
#include <stddef.h>
#include <stdint.h>
#include <sys/types.h>

typedef struct {
    const uint8_t *data;
    size_t bytes;
    uint64_t camera_frame;        /* the source's own counter */
    uint64_t device_timestamp_ns; /* camera clock, 0 if none */
    uint64_t recv_ns;             /* CLOCK_REALTIME when the frame's last byte arrived */
} ft_frame;

/* next() results */
enum { FT_SRC_TIMEOUT = 0, FT_SRC_FRAME = 1, FT_SRC_END = -1, FT_SRC_ERROR = -2 };

typedef struct ft_source ft_source;
struct ft_source {
    /* Waits at most timeout_ms for a frame. A FRAME stays valid until release(). */
    int (*next)(ft_source *s, ft_frame *f, int timeout_ms);
    void (*release)(ft_source *s);
    void (*close)(ft_source *s);
    uint32_t width, height, stride;
    int pixel_format; /* FT_FX_MONO8 / MONO16 / YUYV */
    uint64_t dropped; /* frames the source knows were lost (sequence gaps, bad buffers) */
    char error[200];  /* set with FT_SRC_ERROR (and on open failure) */
    void *priv;
};

/* Requested geometry; 0 = whatever the source says (Y4M header, camera's current setting). */
typedef struct {
    uint32_t width, height;
    int pixel_format;      /* -1 = source's */
    double fps;            /* cameras: frame rate to set, 0 = leave */
    int vanish_timeout_ms; /* cameras: no frame for this long = the camera vanished */
} ft_source_req;

/* All return 0 or -1 with s->error set. */
int ft_source_open_raw(ft_source *s, const char *path, const ft_source_req *req);
int ft_source_open_y4m(ft_source *s, const char *path, const ft_source_req *req);
int ft_source_open_aravis(ft_source *s, const char *camera, const ft_source_req *req);

/* V4L2 talks to the kernel only through this seam. No camera exists on the build machine, so the
 * tests (tests/test_v4l2_seam.c) replace these calls with a fake driver that plays recorded
 * buffers; ft_v4l2_sys_ops is the real kernel. */
typedef struct {
    int (*open)(const char *path, int flags);
    int (*close)(int fd);
    int (*ioctl)(int fd, unsigned long req, void *arg);
    void *(*mmap)(void *addr, size_t len, int prot, int flags, int fd, off_t off);
    int (*munmap)(void *addr, size_t len);
    int (*poll)(struct pollfd *fds, nfds_t n, int timeout_ms);
} ft_v4l2_ops;
extern const ft_v4l2_ops ft_v4l2_sys_ops;
int ft_source_open_v4l2(ft_source *s, const char *device, const ft_source_req *req,
                        const ft_v4l2_ops *ops);

uint64_t ft_now_ns(void); /* CLOCK_REALTIME */

#endif
