/* Event-file readers: opening the input, format detection, text headers, and the read loop that
 * hands the bytes to the per-format decoders (ev_aedat.c, ev_prophesee.c). The input buffer, errors
 * and trigger times that the decoders use too are in ev_input.c, below both. */
#define _POSIX_C_SOURCE 200809L
#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <poll.h>
#include <stdlib.h>
#include <strings.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

#include "ev_internal.h"

static const char *const FORMAT_NAMES[] = {"auto", "aedat2", "aedat3", "aedat4",
                                           "evt2", "evt3",   "dat"};

const char *ft_ev_format_name(int format) {
    if (format < 0 || format > FT_EV_DAT)
        return "unknown";
    return FORMAT_NAMES[format];
}

int ft_ev_format_from_name(const char *name) {
    for (int i = 0; i <= FT_EV_DAT; i++)
        if (name && strcmp(name, FORMAT_NAMES[i]) == 0)
            return i;
    return -1;
}

/* One header line (up to and without '\n' and a '\r' before it) copied into line (truncated to
 * cap - 1); returns 0 at the end of input before a newline (a truncated header). */
static int header_line(ft_ev_reader *r, char *line, size_t cap) {
    size_t i = 0;
    for (;;) {
        if (!ev_need(r, 1))
            return 0;
        const uint8_t *p = r->data + r->start;
        size_t avail = r->end - r->start;
        const uint8_t *nl = memchr(p, '\n', avail);
        size_t take = nl ? (size_t)(nl - p) : avail;
        size_t copy = take < cap - 1 - i ? take : cap - 1 - i;
        memcpy(line + i, p, copy);
        i += copy;
        r->start += take;
        if (nl) {
            r->start++; /* the newline */
            break;
        }
        if (ev_pos(r) > (64u << 20)) /* no newline in 64 MiB: not a header */
            return 0;
    }
    if (i > 0 && line[i - 1] == '\r')
        i--;
    line[i] = 0;
    return 1;
}

static int ends_with(const char *s, const char *suffix) {
    size_t a = strlen(s), b = strlen(suffix);
    return a >= b && strcmp(s + a - b, suffix) == 0;
}

static void chip_geometry(ft_ev_reader *r, const char *line) {
    static const struct {
        const char *name;
        int w, h;
    } chips[] = {{"DVS128", 128, 128},    {"DAVIS240", 240, 180},  {"DAVIS346", 346, 260},
                 {"DAVIS640", 640, 480},  {"DVXplorer", 640, 480}, {"DVXPLORER", 640, 480},
                 {"Tmpdiff128", 128, 128}};
    for (size_t i = 0; i < sizeof chips / sizeof chips[0]; i++)
        if (strstr(line, chips[i].name)) {
            r->info.width = chips[i].w;
            r->info.height = chips[i].h;
            return;
        }
}

/* jAER names the chip class of an AEDAT 2.0 recording in a "# AEChip: <java class>" line, and the
 * class decides how the 32-bit addresses are laid out: reading a DAVIS file with the DVS128 layout
 * gives plausible-looking garbage, so only the chips whose layout is known here are read. Matched
 * on the class's own name (after the last '.'), case-insensitively, by prefix: DAVIS240A/B/C,
 * Davis346B/C/red/blue/cBSI/mini share their family's layout and size. */
static const struct {
    const char *prefix;
    int layout, w, h;
} A2_CHIPS[] = {
    {"DVS128", FT_A2_DVS128, 128, 128},  {"Tmpdiff128", FT_A2_DVS128, 128, 128},
    {"DAVIS240", FT_A2_DAVIS, 240, 180}, {"DAVIS346", FT_A2_DAVIS, 346, 260},
    {"DAVIS640", FT_A2_DAVIS, 640, 480}, {"DAVIS128", FT_A2_DAVIS, 128, 128},
};

static int aedat2_chip(ft_ev_reader *r, const char *line, uint64_t at) {
    const char *v = line + strlen("# AEChip:");
    while (*v == ' ' || *v == '\t')
        v++;
    const char *cls = strrchr(v, '.');
    cls = cls ? cls + 1 : v;
    for (size_t i = 0; i < sizeof A2_CHIPS / sizeof A2_CHIPS[0]; i++)
        if (strncasecmp(cls, A2_CHIPS[i].prefix, strlen(A2_CHIPS[i].prefix)) == 0) {
            r->a2_layout = (uint8_t)A2_CHIPS[i].layout;
            r->info.width = A2_CHIPS[i].w;
            r->info.height = A2_CHIPS[i].h;
            return 0;
        }
    ev_fail(r, at,
            "AEDAT 2.0 AEChip %.80s: its address layout is not known here (read: DVS128, "
            "Tmpdiff128, DAVIS240, DAVIS346, DAVIS640, DAVIS128)",
            cls);
    return -1;
}

/* jAER AEDAT 2.0: '#' lines; the data begins at the first byte that is not '#'. A file without an
 * AEChip line is read as a DVS128, the chip of the format's early years. */
static int header_aedat2(ft_ev_reader *r) {
    char line[512];
    r->a2_layout = FT_A2_DVS128;
    r->info.width = r->info.height = 128;
    while (ev_need(r, 1) && r->data[r->start] == '#') {
        uint64_t at = ev_pos(r);
        if (!header_line(r, line, sizeof line)) {
            ev_fail(r, at, "AEDAT 2.0 header line without its end");
            return -1;
        }
        if (strncmp(line, "# AEChip:", 9) == 0 && aedat2_chip(r, line, at) < 0)
            return -1;
    }
    return r->failed ? -1 : 0;
}

/* AEDAT 3.1: '#' lines up to "#!END-HEADER". */
static int header_aedat3(ft_ev_reader *r) {
    char line[512];
    for (;;) {
        uint64_t at = ev_pos(r);
        if (!header_line(r, line, sizeof line)) {
            ev_fail(r, at, "AEDAT 3.1 header without #!END-HEADER");
            return -1;
        }
        if (strncmp(line, "#Source", 7) == 0)
            chip_geometry(r, line);
        if (strcmp(line, "#!END-HEADER") == 0)
            return 0;
        if (line[0] != '#') {
            ev_fail(r, at, "AEDAT 3.1 header line not starting with '#'");
            return -1;
        }
    }
}

static void prophesee_geometry(ft_ev_reader *r, const char *line) {
    const char *p;
    int a, b;
    if ((p = strstr(line, "geometry")) && sscanf(p + 8, " %dx%d", &a, &b) == 2) {
        r->info.width = a;
        r->info.height = b;
    }
    if ((p = strstr(line, "width=")) && sscanf(p + 6, "%d", &a) == 1)
        r->info.width = a;
    if ((p = strstr(line, "height=")) && sscanf(p + 7, "%d", &a) == 1)
        r->info.height = a;
    if (strncmp(line, "% Width ", 8) == 0 && sscanf(line + 8, "%d", &a) == 1)
        r->info.width = a;
    if (strncmp(line, "% Height ", 9) == 0 && sscanf(line + 9, "%d", &a) == 1)
        r->info.height = a;
}

/* Prophesee RAW (EVT 2/3) and DAT: '%' lines, an optional "% end"; returns the format the header
 * names (or the one asked for). DAT files then carry two bytes: event type and event size. */
static int header_prophesee(ft_ev_reader *r, int asked) {
    char line[512];
    int named = 0;
    while (ev_need(r, 1) && r->data[r->start] == '%') {
        uint64_t at = ev_pos(r);
        if (!header_line(r, line, sizeof line)) {
            ev_fail(r, at, "Prophesee header line without its end");
            return -1;
        }
        prophesee_geometry(r, line);
        if (strncmp(line, "% time_offset_us ", 17) == 0) {
            /* what the EVT 3.0 writer took off every time (see ev_writer.c): added back; a value
             * out of range (past 2^62 us, where the decoders' sums could overflow) is ignored */
            char *end;
            errno = 0;
            long long off = strtoll(line + 17, &end, 10);
            if (errno == 0 && end != line + 17 && off > 0 && off < (1ll << 62)) {
                r->info.time_offset = off;
                r->t_base = off;
            }
        }
        if (strstr(line, "evt 3.0") || strstr(line, "EVT3") || strstr(line, "evt3"))
            named = FT_EV_EVT3;
        else if (strstr(line, "evt 2.0") || strstr(line, "EVT2") || strstr(line, "evt2"))
            named = FT_EV_EVT2;
        if (strcmp(line, "% end") == 0)
            break;
    }
    if (r->failed)
        return -1;
    int fmt = asked ? asked : named;
    if (!fmt && ends_with(r->name, ".dat"))
        fmt = FT_EV_DAT;
    if (!fmt) {
        ev_fail(r, ev_pos(r),
                "Prophesee header names no EVT version (pass the format: evt2, "
                "evt3 or dat)");
        return -1;
    }
    if (fmt == FT_EV_DAT) {
        uint64_t at = ev_pos(r);
        if (!ev_need(r, 2)) {
            ev_fail(r, at, "DAT file ends before its event type and size bytes");
            return -1;
        }
        uint8_t size = r->data[r->start + 1];
        if (size != 8) {
            ev_fail(r, at + 1, "DAT event size %u (only 8-byte CD events are read)", size);
            return -1;
        }
        r->start += 2;
    }
    return fmt;
}

static int detect_and_header(ft_ev_reader *r, int asked) {
    int fmt = asked;
    if (ev_need(r, 12) && memcmp(r->data + r->start, "#!AER-DAT", 9) == 0) {
        const char *v = (const char *)r->data + r->start + 9;
        int f = memcmp(v, "2.0", 3) == 0   ? FT_EV_AEDAT2
                : memcmp(v, "3.1", 3) == 0 ? FT_EV_AEDAT3
                : memcmp(v, "4.0", 3) == 0 ? FT_EV_AEDAT4
                                           : 0;
        if (!f) {
            ev_fail(r, 9, "unsupported AEDAT version '%.3s' (2.0, 3.1, 4.0 are read)", v);
            return -1;
        }
        if (asked && asked != f) {
            ev_fail(r, 0, "the file is %s, not %s", ft_ev_format_name(f), ft_ev_format_name(asked));
            return -1;
        }
        fmt = f;
    } else if (!r->failed && ev_need(r, 1) && r->data[r->start] == '%') {
        if (asked && asked != FT_EV_EVT2 && asked != FT_EV_EVT3 && asked != FT_EV_DAT) {
            ev_fail(r, 0, "the file has a Prophesee header, it is not %s",
                    ft_ev_format_name(asked));
            return -1;
        }
        fmt = header_prophesee(r, asked);
        if (fmt < 0)
            return -1;
        r->info.format = fmt;
        return 0;
    } else if (!asked) {
        if (r->failed)
            return -1;
        ev_fail(r, 0, "unknown event file format (no #!AER-DAT or %% header); pass the format");
        return -1;
    }
    r->info.format = fmt;
    switch (fmt) {
    case FT_EV_AEDAT2:
        return header_aedat2(r);
    case FT_EV_AEDAT3:
        return header_aedat3(r);
    case FT_EV_AEDAT4:
        return ev_aedat4_header(r);
    case FT_EV_DAT:
        return header_prophesee(r, FT_EV_DAT) < 0 ? -1 : 0;
    default: /* headerless EVT 2/3 (format given) */
        return 0;
    }
}

static ft_ev_reader *reader_new(const char *name) {
    ft_ev_reader *r = calloc(1, sizeof *r);
    if (!r)
        return NULL;
    r->fd = -1;
    r->err_off = -1;
    r->table_pos = -1;
    r->ev_stream = -1;
    snprintf(r->name, sizeof r->name, "%s", name ? name : "<memory>");
    return r;
}

static ft_ev_reader *finish_open(ft_ev_reader *r, int format, char *err, size_t err_len) {
    if (format < 0 || format > FT_EV_DAT) {
        snprintf(err, err_len, "%s: unknown format code %d", r->name, format);
        ft_ev_close(r);
        return NULL;
    }
    if (detect_and_header(r, format) < 0) {
        snprintf(err, err_len, "%s", r->err);
        ft_ev_close(r);
        return NULL;
    }
    return r;
}

ft_ev_reader *ft_ev_open(const char *path, int format, char *err, size_t err_len) {
    ft_ev_reader *r = reader_new(path);
    if (!r) {
        snprintf(err, err_len, "%s: out of memory", path);
        return NULL;
    }
    r->fd = open(path, O_RDONLY);
    if (r->fd < 0) {
        snprintf(err, err_len, "%s: cannot open: %s", path, strerror(errno));
        free(r);
        return NULL;
    }
    /* A regular file is mapped (no copy through read(); its pages are the page cache's, clean and
     * reclaimable, so memory stays bounded); pipes and the like are read in chunks. */
    struct stat st;
    if (fstat(r->fd, &st) == 0 && S_ISREG(st.st_mode) && st.st_size > 0) {
        void *map = mmap(NULL, (size_t)st.st_size, PROT_READ, MAP_PRIVATE, r->fd, 0);
        if (map != MAP_FAILED) {
            posix_madvise(map, (size_t)st.st_size, POSIX_MADV_SEQUENTIAL);
            r->map = map;
            r->map_len = (size_t)st.st_size;
            r->data = map;
            r->end = r->map_len;
            r->eof = 1;
            return finish_open(r, format, err, err_len);
        }
    }
    r->buf_cap = FT_EV_READ_CHUNK + 4096;
    r->buf = malloc(r->buf_cap);
    if (!r->buf) {
        snprintf(err, err_len, "%s: out of memory", path);
        ft_ev_close(r);
        return NULL;
    }
    r->data = r->buf;
    return finish_open(r, format, err, err_len);
}

ft_ev_reader *ft_ev_open_mem(const uint8_t *buf, size_t len, int format, const char *name,
                             char *err, size_t err_len) {
    ft_ev_reader *r = reader_new(name);
    if (!r) {
        snprintf(err, err_len, "out of memory");
        return NULL;
    }
    r->data = buf;
    r->end = len;
    r->eof = 1;
    return finish_open(r, format, err, err_len);
}

static size_t word_size(int format) {
    switch (format) {
    case FT_EV_AEDAT2:
    case FT_EV_DAT:
        return 8;
    case FT_EV_EVT2:
        return 4;
    default:
        return 2;
    }
}

long long ft_ev_read(ft_ev_reader *r, ft_event *out, size_t cap) {
    size_t n = 0;
    if (cap < 16) {
        ev_fail(r, ev_pos(r), "ft_ev_read needs room for at least 16 events");
        return -1;
    }
    int fmt = r->info.format;
    while (n + 16 <= cap) {
        if (fmt == FT_EV_AEDAT3 || fmt == FT_EV_AEDAT4) {
            if (r->pend_i < r->pend_n) {
                n = ev_drain_pending(r, out, n, cap);
                continue;
            }
            if (r->failed)
                break;
            if (n > 0 && r->fd >= 0 && !r->map)
                break; /* read from a pipe: return what came before waiting for more */
            int rc = fmt == FT_EV_AEDAT3 ? ev_next_packet_aedat3(r) : ev_next_packet_aedat4(r);
            if (rc <= 0)
                break;
            continue;
        }
        if (r->failed)
            break;
        size_t before = r->start;
        switch (fmt) {
        case FT_EV_AEDAT2:
            n = ev_decode_aedat2(r, out, n, cap);
            break;
        case FT_EV_EVT2:
            n = ev_decode_evt2(r, out, n, cap);
            break;
        case FT_EV_EVT3:
            n = ev_decode_evt3(r, out, n, cap);
            break;
        default:
            n = ev_decode_dat(r, out, n, cap);
            break;
        }
        if (r->failed || n + 16 > cap)
            break;
        size_t ws = word_size(fmt);
        if (r->end - r->start < ws && n > 0 && r->fd >= 0 && !r->map)
            break; /* read from a pipe: return what came before waiting for more */
        if (r->end - r->start < ws && !ev_need(r, ws)) {
            if (r->end > r->start && !r->failed)
                ev_fail(r, ev_pos(r), "truncated file: %s word cut short (%zu of %zu bytes)",
                        ft_ev_format_name(fmt), r->end - r->start, ws);
            break;
        }
        if (r->start == before && r->end - r->start < ws)
            break; /* no progress possible */
    }
    r->info.n_events += n;
    if (n > 0)
        return (long long)n;
    return r->failed ? -1 : 0;
}

int ft_ev_poll(ft_ev_reader *r, int timeout_ms) {
    if (r->fd < 0 || r->map || r->eof || r->failed || r->pend_i < r->pend_n)
        return 1;
    /* a whole word buffered: work to do; a part of one: wait for the rest like for new input */
    int fmt = r->info.format;
    if (fmt != FT_EV_AEDAT3 && fmt != FT_EV_AEDAT4 && r->end - r->start >= word_size(fmt))
        return 1;
    struct pollfd pfd = {r->fd, POLLIN, 0};
    return poll(&pfd, 1, timeout_ms) > 0; /* readable, or the writer hung up (then the end) */
}

void ft_ev_get_info(const ft_ev_reader *r, ft_ev_info *info) {
    *info = r->info;
    info->offset = ev_pos(r);
}

const char *ft_ev_error(const ft_ev_reader *r) {
    return r->failed ? r->err : "";
}
long long ft_ev_error_offset(const ft_ev_reader *r) {
    return r->failed ? r->err_off : -1;
}

void ft_ev_close(ft_ev_reader *r) {
    if (!r)
        return;
    if (r->map)
        munmap(r->map, r->map_len);
    if (r->fd >= 0)
        close(r->fd);
    ev_aedat4_free(r);
    free(r->buf);
    free(r->trig);
    free(r);
}

void ft_ev_keep_triggers(ft_ev_reader *r, int keep) {
    r->keep_triggers = keep != 0;
}

size_t ft_ev_triggers(ft_ev_reader *r, ft_ev_trigger *out, size_t cap) {
    size_t n = r->trig_n < cap ? r->trig_n : cap;
    if (n)
        memcpy(out, r->trig, n * sizeof *out);
    if (n < r->trig_n)
        memmove(r->trig, r->trig + n, (r->trig_n - n) * sizeof *out);
    r->trig_n -= n;
    return n;
}
