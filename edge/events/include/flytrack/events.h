/* libflytrack_events: event-camera files, read in bounded chunks and written.
 *
 * Reads AEDAT 2.0 (jAER: the DVS128 and DAVIS address layouts, by the header's AEChip), AEDAT 3.1
 * (polarity packets), AEDAT 4.0 (event packets, uncompressed, LZ4 frame or Zstd), Prophesee
 * EVT 2.0, EVT 3.0 and DAT. Writes AEDAT 4.0 (readable by dv-processing) and EVT 3.0. Every reader
 * turns its format into one layout, ft_event, and streams: memory stays bounded by the largest
 * packet of the file, whatever its size.
 *
 * Damage: a reader that meets a truncated or corrupt unit (word, packet, header) first returns
 * every event before it, then fails with a message that names the byte offset of the damaged unit
 * (ft_ev_error, ft_ev_error_offset). It never reads outside its buffers, on any input (fuzzed
 * under ASan + UBSan in tests/fuzz_events.c).
 *
 * Typical use:
 *     char err[256];
 *     ft_ev_reader *r = ft_ev_open("rec.aedat4", FT_EV_AUTO, err, sizeof err);
 *     ft_event ev[4096];
 *     long long n;
 *     while ((n = ft_ev_read(r, ev, 4096)) > 0) { ... }
 *     if (n < 0) fprintf(stderr, "%s\n", ft_ev_error(r));
 *     ft_ev_close(r);
 */
#ifndef FLYTRACK_EVENTS_H
#define FLYTRACK_EVENTS_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* One change-detection event; 16 bytes, the NumPy dtype EVENT_DTYPE of flytrack_host.dvs.events. */
typedef struct {
    int64_t t;  /* microseconds, the file's own time base, made monotonic across counter wraps */
    uint16_t x; /* column, 0 = left as the format defines it */
    uint16_t y; /* row */
    uint8_t p;  /* polarity: 1 = ON (brighter), 0 = OFF */
    uint8_t pad[3];
} ft_event;

typedef enum {
    FT_EV_AUTO = 0, /* detect from the header (and the file name for headerless Prophesee files) */
    FT_EV_AEDAT2 = 1,
    FT_EV_AEDAT3 = 2,
    FT_EV_AEDAT4 = 3,
    FT_EV_EVT2 = 4,
    FT_EV_EVT3 = 5,
    FT_EV_DAT = 6,
} ft_ev_format;

/* AEDAT 4.0 compression (IOHeader's CompressionType values). */
typedef enum {
    FT_EV_COMP_NONE = 0,
    FT_EV_COMP_LZ4 = 1,
    FT_EV_COMP_LZ4_HIGH = 2,
    FT_EV_COMP_ZSTD = 3,
    FT_EV_COMP_ZSTD_HIGH = 4,
} ft_ev_compression;

typedef struct {
    int format;          /* ft_ev_format */
    int width, height;   /* sensor size from the header, 0 when the file does not say */
    int compression;     /* AEDAT 4.0 only */
    uint64_t n_events;   /* events returned so far */
    uint64_t n_triggers; /* external trigger / sync events seen so far (not returned as events) */
    uint64_t n_skipped;  /* units of other kinds skipped (other AEDAT packet types, EVT OTHERS) */
    uint64_t offset;     /* bytes of the file consumed so far */
    int64_t time_offset; /* Prophesee header "% time_offset_us" (added to every time), else 0 */
} ft_ev_info;

typedef struct ft_ev_reader ft_ev_reader;

/* Opens a file; NULL on failure with the reason in err. format = FT_EV_AUTO to detect. */
ft_ev_reader *ft_ev_open(const char *path, int format, char *err, size_t err_len);
/* Reads from memory (not copied: keep buf alive until close). name is only used to detect the
 * format by extension and in messages; it may be NULL. */
ft_ev_reader *ft_ev_open_mem(const uint8_t *buf, size_t len, int format, const char *name,
                             char *err, size_t err_len);
/* Fills out with up to cap events (cap >= 16). Returns the number written, 0 at the clean end of
 * the file, -1 once the reader has met damage (after returning every event before it). */
long long ft_ev_read(ft_ev_reader *r, ft_event *out, size_t cap);
/* Streams (a pipe, "/dev/stdin"): ft_ev_read returns the events that have arrived rather than wait
 * to fill out; ft_ev_poll waits at most timeout_ms for input, 1 when ft_ev_read has something to
 * do (always for files and memory), 0 on timeout. */
int ft_ev_poll(ft_ev_reader *r, int timeout_ms);
void ft_ev_get_info(const ft_ev_reader *r, ft_ev_info *info);
const char *ft_ev_error(const ft_ev_reader *r);      /* "" when none */
long long ft_ev_error_offset(const ft_ev_reader *r); /* -1 when none */
void ft_ev_close(ft_ev_reader *r);

/* External trigger / sync events (the frame trigger recorded by the camera: EVT 2.0/3.0
 * EXT_TRIGGER, AEDAT 2.0 sync bit 15 and special bit 31, AEDAT 3.1 external input edges and
 * pulses, AEDAT 4.0 trigger streams' external-signal edges and pulses). Counted always, except
 * AEDAT 4.0's (another stream, decoded only when kept); their times are kept only after
 * ft_ev_keep_triggers(r, 1), and ft_ev_triggers moves them out oldest first, so memory grows
 * only by what the caller has not collected (16 bytes a trigger). */
typedef struct {
    int64_t t;       /* microseconds, the events' time base */
    uint8_t value;   /* 1: rising edge, pulse or sync; 0: falling edge */
    uint8_t channel; /* trigger input id where the format has one, else 0 */
    uint8_t pad[6];
} ft_ev_trigger;
void ft_ev_keep_triggers(ft_ev_reader *r, int keep);
/* Moves up to cap kept triggers into out; returns how many. */
size_t ft_ev_triggers(ft_ev_reader *r, ft_ev_trigger *out, size_t cap);

const char *ft_ev_format_name(int format); /* "aedat2", "aedat3", "aedat4", "evt2", "evt3", "dat" */
int ft_ev_format_from_name(const char *name); /* the reverse, -1 if unknown */

/* Writers: AEDAT 4.0 (compression = ft_ev_compression) or EVT 3.0 (compression ignored). Events
 * must come in non-decreasing time (both formats are time-ordered): a step back (or an EVT 3.0
 * address over 2047) makes ft_ev_write return -1 with the reason in ft_ev_writer_error, nothing of
 * that call written, and the writer stays usable. An I/O error fails the writer for good.
 * ft_ev_writer_close flushes, frees, and returns 0, or -1 with the I/O error in err. */
typedef struct ft_ev_writer ft_ev_writer;
ft_ev_writer *ft_ev_writer_open(const char *path, int format, int width, int height,
                                int compression, char *err, size_t err_len);
/* The same with flags: FT_EV_W_TRIGGERS declares an AEDAT 4.0 trigger stream (stream 1, dv's
 * TriggerPacket "TRIG") for ft_ev_write_triggers; EVT 3.0 takes triggers without it. */
enum { FT_EV_W_TRIGGERS = 1 };
ft_ev_writer *ft_ev_writer_open_ex(const char *path, int format, int width, int height,
                                   int compression, unsigned flags, char *err, size_t err_len);
int ft_ev_write(ft_ev_writer *w, const ft_event *ev, size_t n);
/* External triggers, in non-decreasing time as the readers return them (ft_ev_triggers). EVT 3.0:
 * EXT_TRIGGER words (channel, edge) placed among the events by time: held until an event at or
 * after their time is written, or the writer is closed. AEDAT 4.0: a TriggerPacket of external
 * signal rising (value 1) and falling (0) edges; it has no channel id, which is not kept. Returns
 * how many triggers the format cannot hold and were left out (a negative time, one before what is
 * already written: EVT 3.0 the last event or trigger, AEDAT 4.0 the last trigger; EVT 3.0 a channel
 * over 15), or -1 with the reason in ft_ev_writer_error (AEDAT 4.0 opened without
 * FT_EV_W_TRIGGERS, nothing written; an I/O error fails the writer for good). */
long long ft_ev_write_triggers(ft_ev_writer *w, const ft_ev_trigger *tr, size_t n);
/* EVT 3.0: the whole 2^24 us ranges before the first event, taken off every time written and kept
 * in the header as "% time_offset_us" (ft_ev_open adds it back); 0 for AEDAT 4.0, and until the
 * first event is written. */
int64_t ft_ev_writer_time_offset(const ft_ev_writer *w);
const char *ft_ev_writer_error(const ft_ev_writer *w);
int ft_ev_writer_close(ft_ev_writer *w, char *err, size_t err_len);

#ifdef __cplusplus
}
#endif
#endif
