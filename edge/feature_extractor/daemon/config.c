/* Configuration of flytrack-edge. Each option exists as a flag (--name value) and as a TOML key
 * (name = value, '-' or '_' alike); a TOML file's [sections] only group keys. */
#include "config.h"

#include <arpa/inet.h>
#include <ctype.h>
#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

typedef struct {
    const char *name;
    const char *arg;
    const char *help;
} opt_doc;

static const opt_doc docs[] = {
    {"config", "FILE", "read options from a TOML file (flags given too win)"},
    {"source", "KIND",
     "frame source: raw, y4m, v4l2, aravis (default raw); event source: events (an event "
     "file: AEDAT 2/3/4, EVT 2/3, DAT) or dvs128 (a DVS128 on USB, libusb); events go out in "
     "DVS_CLUSTERS slices"},
    {"input", "WHERE",
     "raw/y4m: file or - for stdin (default -); v4l2: device (/dev/video0); "
     "aravis: camera name as Aravis lists it (e.g. Aravis-Fake-<serial>) or IP"},
    {"width", "PX",
     "frame width (raw: required; others: set on the camera, or 0 = as is). Raw from a "
     "pipe: a wrong --width/--height/--pixel-format misaligns frames silently (a file's size "
     "is checked; a pipe only fails if it ends inside a frame)"},
    {"height", "PX", "frame height"},
    {"pixel-format", "FMT", "mono8, mono16 (little-endian) or yuyv (luma used); default mono8"},
    {"fps", "HZ", "cameras: frame rate to set (0 = leave as is)"},
    {"vanish-timeout-ms", "MS", "cameras: no frame for this long = camera vanished (default 5000)"},
    {"host", "ADDR", "host receiving FEATURES, STATUS, IMAGE (default 127.0.0.1)"},
    {"port", "N", "its UDP port (default 7700)"},
    {"bind", "ADDR", "local address of the edge's socket (default 0.0.0.0)"},
    {"control-allow", "ADDR[,ADDR]",
     "accept CONTROL only from these IPv4 senders (repeatable; 'loopback' = 127.0.0.0/8, "
     "'any' = all); default: the --host address and loopback. Others are dropped and counted"},
    {"control-port", "N",
     "local UDP port for CONTROL; features are sent from it too (default 7701, "
     "0 = any free port)"},
    {"camera-index", "N", "this camera's index in the rig file (default 0)"},
    {"camera-name", "NAME", "name sent in STATUS (default: the input)"},
    {"truncate", "0|1",
     "more than 32 points: send the strongest 32 flagged TRUNCATED (1) or split "
     "over several datagrams (0, default)"},
    {"start-stopped", "0|1", "wait for a CONTROL START before extracting (default 0)"},
    {"status-interval-ms", "MS", "STATUS heartbeat period (default 1000)"},
    {"regions", "HALF", "send an IMAGE region of half-size HALF px around each point (0 = off)"},
    {"max-frames", "N", "exit after N frames (0 = run until the source ends)"},
    {"mask", "FILE", "mask image: width x height raw bytes, nonzero = pixel used"},
    {"alpha", "A", "background running-average weight (default 0.01)"},
    {"n-sigma", "N", "candidate must exceed N x the pixel's background std (default 7)"},
    {"diff-threshold", "D", "candidate must exceed this absolute difference (default 30)"},
    {"bg-update-interval", "N", "update the background every N frames (default 200, 0 = never)"},
    {"polarity", "P", "both, bright or dark differences (default both)"},
    {"clear-fraction", "F", "clear pixels below F x the region's peak difference (default 0.3)"},
    {"despeckle-threshold", "D", "clear pixels whose difference is below D (default 5)"},
    {"min-area", "N", "drop regions with fewer than N kept pixels (default 1)"},
    {"subtract-cut", "0|1", "moment weights = difference - cut (1, default) or difference (0)"},
    {"max-points", "N",
     "at most N points per frame, strongest first (default 100, <= 8160 = 255 parts x 32)"},
    {"max-candidates", "N", "candidate pixels examined per frame (default 65536)"},
    {"intrinsics", "FX,FY,CX,CY[,SKEW]", "camera matrix for lens-distortion correction"},
    {"distortion", "K1,K2,P1,P2,K3", "OpenCV distortion coefficients (as host camera.py)"},
    {"verbose", "0|1", "log every control message and source event"},
    {"event-format", "FMT", "events: aedat2, aedat3, aedat4, evt2, evt3, dat or auto (default)"},
    {"slice-us", "US", "event sources: event time per DVS_CLUSTERS slice (default 1000)"},
    {"ba-window-us", "US",
     "event sources: background-activity filter window (default 2000, libcaer's; a smaller sensor "
     "sees an animal's events sparser: e.g. 346/128 x 2000 for a DVS128)"},
    {"cluster-min-mass", "M",
     "event sources: support (events decayed over 10 ms) a cluster needs to be reported (default "
     "5; "
     "a smaller sensor gets fewer events of an animal: e.g. 5 x 128/346 for a DVS128)"},
    {"realtime", "0|1",
     "events: play the file at its recorded pace (1, default) or at once (0); with --input - "
     "(stdin, e.g. a live producer) events are taken as they arrive"},
    {"reopen-ms", "MS", "dvs128: while unplugged, try to reopen it this often (default 500)"},
    {"dvs-biases", "HEX", "dvs128: 72 hex digits, the 12 x 3 bias bytes to send (default: keep)"},
    {"dvs-invert-polarity", "0|1",
     "dvs128: 1 for an original DVS128, whose raw polarity bit 1 means OFF (jAER, libcaer); 0 "
     "(default) for the FlyTrack bridge, whose words follow the SPEC (1 = ON)"},
    {"wingbeat", "0|1",
     "event sources: track the wing beats of a tethered fly (seed 002 part II: 2-means "
     "initialisation, an EKF on a Fourier series per wing edge) and send DVS_WINGBEAT instead "
     "of DVS_CLUSTERS (default 0)"},
    {"wingbeat-report-us", "US", "wingbeat: a DVS_WINGBEAT every US of event time (default 5000)"},
    {"wingbeat-harmonics", "K", "wingbeat: Fourier harmonics of the EKF, 1..4 (default 2)"},
    {"wingbeat-events-per-update", "N", "wingbeat: events averaged per EKF update (default 4)"},
    {"wingbeat-init-us", "US", "wingbeat: initialisation window of event time (default 100000)"},
    {"wingbeat-start-freq", "HZ",
     "wingbeat: starting beat frequency (default 0: found in the initialisation window)"},
};

static void usage(const char *prog) {
    printf(
        "usage: %s [options]\n\n"
        "flytrack-edge: reads camera frames, extracts 2D feature points (libflytrack_features) "
        "and\n"
        "sends one FEATURES datagram per frame to the host (protocol/SPEC.md), a STATUS "
        "heartbeat,\n"
        "and obeys CONTROL messages (set parameter, new background, full frame, regions, start,\n"
        "stop) with a CONTROL_ACK. Exit status: 0 done (source ended, --max-frames, SIGINT/TERM),\n"
        "2 bad configuration, 3 source failed (cannot open, vanished, ended inside a frame).\n"
        "Event sources (--source events | dvs128) send DVS_CLUSTERS per time slice instead of\n"
        "FEATURES; a DVS128 unplugged while running is reopened when it comes back.\n\n"
        "options (also TOML keys in --config FILE):\n",
        prog);
    for (size_t i = 0; i < sizeof docs / sizeof docs[0]; i++) {
        char left[64];
        snprintf(left, sizeof left, "--%s %s", docs[i].name, docs[i].arg);
        /* Wrap the help at about 64 columns, continuation lines under the first. */
        const char *h = docs[i].help;
        int first = 1;
        while (*h) {
            int n = (int)strlen(h);
            if (n > 64) {
                n = 64;
                while (n > 0 && h[n] != ' ')
                    n--;
                if (n == 0)
                    n = 64;
            }
            printf("  %-34s %.*s\n", first ? left : "", n, h);
            first = 0;
            h += n;
            while (*h == ' ')
                h++;
        }
    }
    printf("  %-34s %s\n", "--help", "this text");
}

static int err(const char *key, const char *val, const char *why) {
    fprintf(stderr, "flytrack-edge: option %s = \"%s\": %s\n", key, val, why);
    return -1;
}

static int parse_double(const char *key, const char *v, double *out) {
    char *end;
    errno = 0;
    double d = strtod(v, &end);
    if (errno || end == v || *end || !isfinite(d))
        return err(key, v, "not a finite number");
    *out = d;
    return 0;
}

static int parse_int(const char *key, const char *v, long long lo, long long hi, long long *out) {
    char *end;
    errno = 0;
    long long n = strtoll(v, &end, 10);
    if (errno || end == v || *end)
        return err(key, v, "not an integer");
    if (n < lo || n > hi) {
        char why[80];
        snprintf(why, sizeof why, "must be in %lld..%lld", lo, hi);
        return err(key, v, why);
    }
    *out = n;
    return 0;
}

static int parse_bool(const char *key, const char *v, int *out) {
    if (!strcmp(v, "1") || !strcmp(v, "true") || !strcmp(v, "yes"))
        *out = 1;
    else if (!strcmp(v, "0") || !strcmp(v, "false") || !strcmp(v, "no"))
        *out = 0;
    else
        return err(key, v, "must be true/false or 1/0");
    return 0;
}

static int parse_list(const char *key, const char *v, double *out, int min_n, int max_n) {
    char buf[256];
    snprintf(buf, sizeof buf, "%s", v);
    int n = 0;
    for (char *tok = strtok(buf, ", "); tok; tok = strtok(NULL, ", ")) {
        if (n == max_n)
            return err(key, v, "too many numbers");
        if (parse_double(key, tok, &out[n++]))
            return -1;
    }
    if (n < min_n)
        return err(key, v, "too few numbers");
    return 0;
}

/* --control-allow: IPv4 addresses, "loopback" or "any", comma or space separated; adds to earlier
 * ones (the option is repeatable, and a config file's list adds to the flags'). */
static int parse_allow(edge_config *c, const char *key, const char *v) {
    char buf[512];
    if (strlen(v) >= sizeof buf)
        return err(key, v, "too long");
    snprintf(buf, sizeof buf, "%s", v);
    int n = 0;
    /* Quotes count as separators too: a TOML array of strings ["a", "b"] arrives as "a", "b". */
    for (char *tok = strtok(buf, ", \"'"); tok; tok = strtok(NULL, ", \"'"), n++) {
        struct in_addr a;
        if (!strcmp(tok, "any"))
            c->control_allow_any = 1;
        else if (!strcmp(tok, "loopback"))
            c->control_allow_loopback = 1;
        else if (inet_pton(AF_INET, tok, &a) != 1)
            return err(key, v, "not an IPv4 address (or 'loopback', 'any')");
        else if (c->n_control_allow == EDGE_MAX_CONTROL_ALLOW)
            return err(key, v, "more than 16 addresses");
        else
            c->control_allow[c->n_control_allow++] = a.s_addr;
    }
    if (!n)
        return err(key, v, "needs an address");
    return 0;
}

static int copy_str(const char *key, const char *v, char *dst, size_t cap) {
    if (strlen(v) >= cap)
        return err(key, v, "too long");
    snprintf(dst, cap, "%s", v);
    return 0;
}

/* Applies one option; key uses '-' (TOML '_' is mapped before). */
static int apply(edge_config *c, const char *key, const char *v) {
    long long n;
    double d;
    int b;
#define INT(name, lo, hi, field)                                                                   \
    if (!strcmp(key, name)) {                                                                      \
        if (parse_int(key, v, lo, hi, &n))                                                         \
            return -1;                                                                             \
        c->field = n;                                                                              \
        return 0;                                                                                  \
    }
#define DBL(name, field)                                                                           \
    if (!strcmp(key, name)) {                                                                      \
        if (parse_double(key, v, &d))                                                              \
            return -1;                                                                             \
        c->field = d;                                                                              \
        return 0;                                                                                  \
    }
#define BOOL(name, field)                                                                          \
    if (!strcmp(key, name)) {                                                                      \
        if (parse_bool(key, v, &b))                                                                \
            return -1;                                                                             \
        c->field = b;                                                                              \
        return 0;                                                                                  \
    }
#define STR(name, field)                                                                           \
    if (!strcmp(key, name))                                                                        \
        return copy_str(key, v, c->field, sizeof c->field);
    if (!strcmp(key, "source")) {
        if (strcmp(v, "raw") && strcmp(v, "y4m") && strcmp(v, "v4l2") && strcmp(v, "aravis") &&
            strcmp(v, "events") && strcmp(v, "dvs128"))
            return err(key, v, "unknown source (raw, y4m, v4l2, aravis, events, dvs128)");
        return copy_str(key, v, c->source, sizeof c->source);
    }
    if (!strcmp(key, "pixel-format")) {
        if (!strcmp(v, "mono8"))
            c->pixel_format = FT_FX_MONO8;
        else if (!strcmp(v, "mono16"))
            c->pixel_format = FT_FX_MONO16;
        else if (!strcmp(v, "yuyv"))
            c->pixel_format = FT_FX_YUYV;
        else
            return err(key, v, "unknown pixel format (mono8, mono16, yuyv)");
        return 0;
    }
    if (!strcmp(key, "polarity")) {
        if (!strcmp(v, "both"))
            c->fx.polarity = FT_FX_POLARITY_BOTH;
        else if (!strcmp(v, "bright"))
            c->fx.polarity = FT_FX_POLARITY_BRIGHT;
        else if (!strcmp(v, "dark"))
            c->fx.polarity = FT_FX_POLARITY_DARK;
        else
            return err(key, v, "unknown polarity (both, bright, dark)");
        return 0;
    }
    if (!strcmp(key, "intrinsics")) {
        double k[5] = {0, 0, 0, 0, 0};
        if (parse_list(key, v, k, 4, 5))
            return -1;
        if (k[0] <= 0 || k[1] <= 0)
            return err(key, v, "focal lengths must be > 0");
        memcpy(c->intrinsics, k, sizeof k);
        c->have_intrinsics = 1;
        return 0;
    }
    if (!strcmp(key, "distortion"))
        return parse_list(key, v, c->distortion, 5, 5);
    if (!strcmp(key, "control-allow"))
        return parse_allow(c, key, v);
    if (!strcmp(key, "event-format")) {
        static const char *const fmts[] = {"auto", "aedat2", "aedat3", "aedat4",
                                           "evt2", "evt3",   "dat"};
        for (size_t i = 0; i < sizeof fmts / sizeof fmts[0]; i++)
            if (!strcmp(v, fmts[i]))
                return copy_str(key, v, c->event_format, sizeof c->event_format);
        return err(key, v, "unknown event format (aedat2, aedat3, aedat4, evt2, evt3, dat, auto)");
    }
    if (!strcmp(key, "dvs-biases")) {
        if (strlen(v) != 72)
            return err(key, v, "needs 72 hex digits (12 biases x 3 bytes)");
        for (int i = 0; i < 36; i++) {
            unsigned byte;
            if (!isxdigit((unsigned char)v[2 * i]) || !isxdigit((unsigned char)v[2 * i + 1]) ||
                sscanf(v + 2 * i, "%2x", &byte) != 1)
                return err(key, v, "not hex");
            c->dvs_biases[i] = (uint8_t)byte;
        }
        c->have_dvs_biases = 1;
        return 0;
    }
    INT("slice-us", 1, 10000000, slice_us)
    INT("ba-window-us", 1, 10000000, ba_window_us)
    if (!strcmp(key, "cluster-min-mass")) {
        if (parse_double(key, v, &d))
            return -1;
        if (!(d >= 0.5 && d <= 1e6)) /* under 0.5 a cluster would never die (DEATH_MASS) */
            return err(key, v, "must be 0.5 .. 1000000");
        c->cluster_min_mass = d;
        return 0;
    }
    BOOL("wingbeat", wingbeat)
    INT("wingbeat-report-us", 100, 10000000, wingbeat_report_us)
    INT("wingbeat-harmonics", 1, 4, wingbeat_harmonics)
    INT("wingbeat-events-per-update", 1, 1000, wingbeat_events_per_update)
    INT("wingbeat-init-us", 20000, 10000000, wingbeat_init_us)
    if (!strcmp(key, "wingbeat-start-freq")) {
        if (parse_double(key, v, &d))
            return -1;
        if (d < 0 || d > 10000)
            return err(key, v, "a frequency in Hz, 0..10000 (0 = found from the events)");
        c->wingbeat_start_freq = d;
        return 0;
    }
    BOOL("realtime", realtime)
    BOOL("dvs-invert-polarity", dvs_invert_polarity)
    INT("reopen-ms", 10, 3600000, reopen_ms)
    STR("input", input)
    INT("width", 0, 16384, width)
    INT("height", 0, 16384, height)
    DBL("fps", fps)
    INT("vanish-timeout-ms", 0, 3600000, vanish_timeout_ms)
    STR("host", host)
    INT("port", 1, 65535, port)
    STR("bind", bind)
    INT("control-port", 0, 65535, control_port)
    INT("camera-index", 0, 65534, camera_index)
    STR("camera-name", camera_name)
    BOOL("truncate", truncate)
    BOOL("start-stopped", start_stopped)
    INT("status-interval-ms", 10, 3600000, status_interval_ms)
    INT("regions", 0, 255, region_half)
    INT("max-frames", 0, (long long)1 << 62, max_frames)
    STR("mask", mask)
    BOOL("verbose", verbose)
    DBL("alpha", fx.alpha)
    DBL("n-sigma", fx.n_sigma)
    DBL("diff-threshold", fx.diff_threshold)
    INT("bg-update-interval", 0, 1 << 30, fx.bg_update_interval)
    DBL("clear-fraction", fx.clear_fraction)
    DBL("despeckle-threshold", fx.despeckle_threshold)
    INT("min-area", 1, 1 << 30, fx.min_area)
    BOOL("subtract-cut", fx.subtract_cut)
    INT("max-points", 1, FT_FX_MAX_POINTS, fx.max_points)
    INT("max-candidates", 1, 1 << 26, fx.max_candidates)
    fprintf(stderr, "flytrack-edge: unknown option \"%s\" (see --help)\n", key);
    return -1;
}

static char *trim(char *s) {
    while (isspace((unsigned char)*s))
        s++;
    char *e = s + strlen(s);
    while (e > s && isspace((unsigned char)e[-1]))
        *--e = 0;
    return s;
}

static int load_toml(edge_config *c, const char *path) {
    FILE *f = fopen(path, "r");
    if (!f) {
        fprintf(stderr, "flytrack-edge: cannot read config %s: %s\n", path, strerror(errno));
        return -1;
    }
    char line[512];
    int lineno = 0, rc = 0;
    while (!rc && fgets(line, sizeof line, f)) {
        lineno++;
        char *s = trim(line);
        if (!*s || *s == '#' || *s == '[')
            continue;
        char *eq = strchr(s, '=');
        if (!eq) {
            fprintf(stderr, "flytrack-edge: %s:%d: expected key = value\n", path, lineno);
            rc = -1;
            break;
        }
        *eq = 0;
        char *key = trim(s), *val = trim(eq + 1);
        if (*val == '"' || *val == '\'') { /* a quoted string: up to the matching quote */
            char q = *val++;
            char *end = strchr(val, q);
            if (!end) {
                fprintf(stderr, "flytrack-edge: %s:%d: unterminated string\n", path, lineno);
                rc = -1;
                break;
            }
            *end = 0;
        } else {
            char *hash = strchr(val, '#');
            if (hash)
                *hash = 0;
            val = trim(val);
            if (*val == '[') { /* an array of numbers: [a, b, c] */
                val++;
                char *end = strchr(val, ']');
                if (end)
                    *end = 0;
            }
        }
        for (char *k = key; *k; k++)
            if (*k == '_')
                *k = '-';
        if (apply(c, key, val)) {
            fprintf(stderr, "flytrack-edge: in %s line %d\n", path, lineno);
            rc = -1;
        }
    }
    fclose(f);
    return rc;
}

int edge_config_load(edge_config *c, int argc, char **argv) {
    memset(c, 0, sizeof *c);
    snprintf(c->source, sizeof c->source, "raw");
    snprintf(c->input, sizeof c->input, "-");
    c->pixel_format = -1;
    c->vanish_timeout_ms = 5000;
    snprintf(c->host, sizeof c->host, "127.0.0.1");
    c->port = 7700;
    snprintf(c->bind, sizeof c->bind, "0.0.0.0");
    c->control_port = 7701;
    c->status_interval_ms = 1000;
    snprintf(c->event_format, sizeof c->event_format, "auto");
    c->slice_us = 1000;
    c->realtime = 1;
    c->reopen_ms = 500;
    c->wingbeat_report_us = 5000;
    c->wingbeat_harmonics = 2;
    c->wingbeat_events_per_update = 4;
    c->wingbeat_init_us = 100000;
    ft_fx_params_default(&c->fx, 1, 1, FT_FX_MONO8);
    for (int i = 1; i < argc; i++)
        if (!strcmp(argv[i], "--help") || !strcmp(argv[i], "-h")) {
            usage(argv[0]);
            return 1;
        }
    for (int i = 1; i < argc; i++) /* the file first, so that flags override it */
        if (!strcmp(argv[i], "--config")) {
            if (i + 1 >= argc)
                return err("--config", "", "needs a file");
            if (load_toml(c, argv[i + 1]))
                return -1;
        }
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i];
        if (strncmp(a, "--", 2) != 0) {
            fprintf(stderr, "flytrack-edge: unexpected argument \"%s\" (see --help)\n", a);
            return -1;
        }
        char key[64];
        const char *val;
        const char *eq = strchr(a, '=');
        if (eq) {
            snprintf(key, sizeof key, "%.*s", (int)(eq - a - 2), a + 2);
            val = eq + 1;
        } else {
            snprintf(key, sizeof key, "%s", a + 2);
            if (i + 1 >= argc) {
                fprintf(stderr, "flytrack-edge: option --%s needs a value\n", key);
                return -1;
            }
            val = argv[++i];
        }
        if (!strcmp(key, "config"))
            continue;
        if (apply(c, key, val))
            return -1;
    }
    if (!c->camera_name[0])
        snprintf(c->camera_name, sizeof c->camera_name, "%.32s", c->input);
    return 0;
}

void edge_config_default_control(edge_config *c, uint32_t host_addr) {
    if (c->n_control_allow || c->control_allow_any || c->control_allow_loopback)
        return; /* the user said who may control this edge */
    c->control_allow[c->n_control_allow++] = host_addr;
    c->control_allow_loopback = 1;
}

int edge_config_control_allowed(const edge_config *c, uint32_t addr) {
    if (c->control_allow_any || (c->control_allow_loopback && (ntohl(addr) >> 24) == 127))
        return 1;
    for (int i = 0; i < c->n_control_allow; i++)
        if (c->control_allow[i] == addr)
            return 1;
    return 0;
}
