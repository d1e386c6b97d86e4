/* Raw 8/16-bit frames and Y4M, from a file or a pipe ("-" = stdin).
 *
 * Streaming: the fd is polled, and each read takes what has arrived into the frame buffer, so a
 * frame is handed over the moment its last byte is in (no read-ahead, no stdio buffering). A stream
 * that ends between frames is END; one that ends inside a frame is an ERROR naming the bytes
 * missing.
 */
#include <errno.h>
#include <stdarg.h>
#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

#include "flytrack/features.h"
#include "source.h"

uint64_t ft_now_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_REALTIME, &ts);
    return (uint64_t)ts.tv_sec * 1000000000ull + (uint64_t)ts.tv_nsec;
}

typedef struct {
    int fd, own_fd, y4m;
    uint8_t *buf;
    size_t frame_bytes; /* bytes of the frame's payload on the stream */
    size_t luma_bytes;  /* the part we use (Y4M: the Y plane) */
    size_t got;
    int in_header; /* Y4M: reading the "FRAME..." line */
    char line[256];
    size_t line_len;
    uint64_t count;
} file_priv;

__attribute__((format(printf, 2, 3))) static int set_err(ft_source *s, const char *fmt, ...) {
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(s->error, sizeof s->error, fmt, ap);
    va_end(ap);
    return -1;
}

/* Reads what is there, up to want bytes; returns bytes read, 0 at EOF, -1 on error, -2 if none yet.
 */
static ssize_t read_some(int fd, void *dst, size_t want, int timeout_ms) {
    struct pollfd p = {.fd = fd, .events = POLLIN};
    int r = poll(&p, 1, timeout_ms);
    if (r < 0)
        return errno == EINTR ? -2 : -1;
    if (r == 0)
        return -2;
    ssize_t n = read(fd, dst, want);
    if (n < 0)
        return (errno == EINTR || errno == EAGAIN) ? -2 : -1;
    return n;
}

static const char *fmt_name(int fmt) {
    return fmt == FT_FX_MONO8 ? "mono8" : fmt == FT_FX_MONO16 ? "mono16" : "yuyv";
}

static int file_next(ft_source *s, ft_frame *f, int timeout_ms) {
    file_priv *fp = s->priv;
    for (;;) {
        if (fp->y4m && fp->in_header) {
            char c;
            ssize_t n = read_some(fp->fd, &c, 1, timeout_ms);
            if (n == -2)
                return FT_SRC_TIMEOUT;
            if (n < 0)
                return set_err(s, "reading the input: %s", strerror(errno)), FT_SRC_ERROR;
            if (n == 0) {
                if (fp->line_len == 0)
                    return FT_SRC_END;
                set_err(s, "Y4M input ended inside a FRAME header");
                return FT_SRC_ERROR;
            }
            if (c != '\n') {
                if (fp->line_len + 1 >= sizeof fp->line) {
                    set_err(s, "Y4M frame header longer than 255 bytes");
                    return FT_SRC_ERROR;
                }
                fp->line[fp->line_len++] = c;
                continue;
            }
            fp->line[fp->line_len] = 0;
            if (strncmp(fp->line, "FRAME", 5) != 0 || (fp->line[5] && fp->line[5] != ' ')) {
                set_err(s,
                        "Y4M: expected FRAME, got \"%.40s\" (frame %llu; frames not of the "
                        "header's size and colour space?)",
                        fp->line, (unsigned long long)fp->count);
                return FT_SRC_ERROR;
            }
            fp->line_len = 0;
            fp->in_header = 0;
            fp->got = 0;
        }
        ssize_t n = read_some(fp->fd, fp->buf + fp->got, fp->frame_bytes - fp->got, timeout_ms);
        if (n == -2)
            return FT_SRC_TIMEOUT;
        if (n < 0) {
            set_err(s, "reading the input: %s", strerror(errno));
            return FT_SRC_ERROR;
        }
        if (n == 0) {
            if (fp->got == 0 && !fp->y4m)
                return FT_SRC_END;
            /* On a pipe this is the only sign of a wrong geometry: name what was expected. */
            if (fp->y4m)
                set_err(s,
                        "input ended inside frame %llu: got %zu of %zu bytes (a %ux%u Y4M frame "
                        "as its header says)",
                        (unsigned long long)fp->count, fp->got, fp->frame_bytes, s->width,
                        s->height);
            else
                set_err(s,
                        "input ended inside frame %llu: got %zu of %zu bytes (%ux%u %s); check "
                        "--width, --height, --pixel-format",
                        (unsigned long long)fp->count, fp->got, fp->frame_bytes, s->width,
                        s->height, fmt_name(s->pixel_format));
            return FT_SRC_ERROR;
        }
        fp->got += (size_t)n;
        if (fp->got < fp->frame_bytes) {
            timeout_ms = 0; /* keep reading what is already there, but do not block twice */
            continue;
        }
        f->recv_ns = ft_now_ns();
        f->data = fp->buf;
        f->bytes = fp->luma_bytes;
        f->camera_frame = fp->count++;
        f->device_timestamp_ns = 0;
        fp->got = 0;
        fp->in_header = fp->y4m;
        return FT_SRC_FRAME;
    }
}

static void file_release(ft_source *s) {
    (void)s;
}

static void file_close(ft_source *s) {
    file_priv *fp = s->priv;
    if (!fp)
        return;
    if (fp->own_fd)
        close(fp->fd);
    free(fp->buf);
    free(fp);
    s->priv = NULL;
}

static int open_fd(ft_source *s, const char *path, file_priv *fp) {
    if (!strcmp(path, "-")) {
        fp->fd = 0;
        return 0;
    }
    fp->fd = open(path, O_RDONLY);
    if (fp->fd < 0)
        return set_err(s, "cannot open %s: %s", path, strerror(errno));
    fp->own_fd = 1;
    return 0;
}

static void init_ops(ft_source *s) {
    s->next = file_next;
    s->release = file_release;
    s->close = file_close;
}

static size_t bpp_of(int fmt) {
    return fmt == FT_FX_MONO8 ? 1 : 2;
}

int ft_source_open_raw(ft_source *s, const char *path, const ft_source_req *req) {
    memset(s, 0, sizeof *s);
    if (!req->width || !req->height) {
        snprintf(s->error, sizeof s->error, "raw input needs --width and --height");
        return -1;
    }
    int fmt = req->pixel_format < 0 ? FT_FX_MONO8 : req->pixel_format;
    file_priv *fp = calloc(1, sizeof *fp);
    if (!fp)
        return set_err(s, "out of memory");
    s->priv = fp;
    init_ops(s);
    s->width = req->width;
    s->height = req->height;
    s->pixel_format = fmt;
    s->stride = (uint32_t)(req->width * bpp_of(fmt));
    fp->frame_bytes = fp->luma_bytes = (size_t)req->width * req->height * bpp_of(fmt);
    if (open_fd(s, path, fp)) {
        file_close(s);
        return -1;
    }
    struct stat st;
    if (fstat(fp->fd, &st) == 0 && S_ISREG(st.st_mode) && (size_t)st.st_size % fp->frame_bytes) {
        snprintf(s->error, sizeof s->error,
                 "%s has %lld bytes, not a whole number of %ux%u frames of %zu bytes: wrong frame "
                 "size or pixel format?",
                 path, (long long)st.st_size, req->width, req->height, fp->frame_bytes);
        file_close(s);
        return -1;
    }
    fp->buf = malloc(fp->frame_bytes);
    if (!fp->buf) {
        file_close(s);
        return set_err(s, "out of memory");
    }
    return 0;
}

/* Y4M stream header: "YUV4MPEG2 W<w> H<h> [F..] [I..] [A..] [C<colour space>] [X..]\n". */
int ft_source_open_y4m(ft_source *s, const char *path, const ft_source_req *req) {
    memset(s, 0, sizeof *s);
    file_priv *fp = calloc(1, sizeof *fp);
    if (!fp)
        return set_err(s, "out of memory");
    s->priv = fp;
    init_ops(s);
    fp->y4m = 1;
    if (open_fd(s, path, fp)) {
        file_close(s);
        return -1;
    }
    char hdr[512];
    size_t n = 0;
    for (;;) { /* the header arrives once, before any frame: blocking byte reads are fine here */
        char c;
        ssize_t r = read(fp->fd, &c, 1);
        if (r < 0 && errno == EINTR)
            continue;
        if (r <= 0) {
            snprintf(s->error, sizeof s->error, "Y4M input %s ended before its header", path);
            file_close(s);
            return -1;
        }
        if (c == '\n')
            break;
        if (n + 1 >= sizeof hdr) {
            snprintf(s->error, sizeof s->error, "Y4M header longer than 511 bytes");
            file_close(s);
            return -1;
        }
        hdr[n++] = c;
    }
    hdr[n] = 0;
    if (strncmp(hdr, "YUV4MPEG2", 9) != 0) {
        snprintf(s->error, sizeof s->error, "%s is not Y4M (no YUV4MPEG2 signature)", path);
        file_close(s);
        return -1;
    }
    long w = 0, h = 0;
    char cs[32] = "420jpeg";
    for (char *tok = strtok(hdr + 9, " "); tok; tok = strtok(NULL, " ")) {
        char *end = NULL;
        if (tok[0] == 'W')
            w = strtol(tok + 1, &end, 10);
        else if (tok[0] == 'H')
            h = strtol(tok + 1, &end, 10);
        else if (tok[0] == 'C')
            snprintf(cs, sizeof cs, "%s", tok + 1);
        if (end && (end == tok + 1 || *end)) {
            snprintf(s->error, sizeof s->error, "Y4M header: bad size field \"%.20s\"", tok);
            file_close(s);
            return -1;
        }
    }
    if (w <= 0 || h <= 0 || w > 16384 || h > 16384) {
        snprintf(s->error, sizeof s->error, "Y4M header has a bad size W%ld H%ld", w, h);
        file_close(s);
        return -1;
    }
    if ((req->width && (long)req->width != w) || (req->height && (long)req->height != h)) {
        snprintf(s->error, sizeof s->error, "Y4M frames are %ldx%ld, but %ux%u was configured", w,
                 h, req->width, req->height);
        file_close(s);
        return -1;
    }
    size_t luma = (size_t)w * (size_t)h, chroma;
    size_t cw = (size_t)(w + 1) / 2, ch = (size_t)(h + 1) / 2;
    if (!strcmp(cs, "mono"))
        chroma = 0;
    else if (!strncmp(cs, "420", 3) && (cs[3] == 0 || !strcmp(cs + 3, "jpeg") ||
                                        !strcmp(cs + 3, "mpeg2") || !strcmp(cs + 3, "paldv")))
        chroma = 2 * cw * ch;
    else if (!strcmp(cs, "422"))
        chroma = 2 * cw * (size_t)h;
    else if (!strcmp(cs, "444"))
        chroma = 2 * luma;
    else {
        snprintf(s->error, sizeof s->error,
                 "Y4M colour space C%s is not supported (8-bit mono, 420, 422, 444 are)", cs);
        file_close(s);
        return -1;
    }
    if (req->pixel_format > 0) {
        snprintf(s->error, sizeof s->error, "Y4M input is 8-bit: use pixel format mono8");
        file_close(s);
        return -1;
    }
    s->width = (uint32_t)w;
    s->height = (uint32_t)h;
    s->stride = (uint32_t)w;
    s->pixel_format = FT_FX_MONO8;
    fp->luma_bytes = luma;
    fp->frame_bytes = luma + chroma;
    fp->in_header = 1;
    fp->buf = malloc(fp->frame_bytes);
    if (!fp->buf) {
        file_close(s);
        return set_err(s, "out of memory");
    }
    return 0;
}
