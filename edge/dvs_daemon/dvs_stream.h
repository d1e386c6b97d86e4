/* DVS128 USB byte stream -> events (protocol/SPEC.md section 2), fed in whatever pieces the bulk
 * transfers deliver: a word split across two transfers is completed from the next one.
 *
 * Each complete word goes through the protocol codec (flytrack/dvs.h): WRAP adds 0x4000 us to the
 * time base, RESET zeroes it, an address event becomes an ft_event (t us, x, y, p = 1 ON), a SYNC
 * word is counted and its time kept. A word the codec rejects (RESET and WRAP both set,
 * ...) is garbage: counted, skipped, and the stream goes on with the next word. */
#ifndef FLYTRACK_EDGE_DVS_STREAM_H
#define FLYTRACK_EDGE_DVS_STREAM_H

#include <stddef.h>
#include <stdint.h>

#include "flytrack/dvs.h"
#include "flytrack/events.h"

typedef struct {
    ft_dvs_decoder dec;
    uint8_t carry[4]; /* the first bytes of a word cut by the end of a transfer */
    size_t n_carry;
    uint64_t words, events, wraps, resets, syncs, bad_words;
#define FT_DVS_STREAM_SYNCS 256
    int64_t
        sync_t[FT_DVS_STREAM_SYNCS]; /* times of the latest SYNC words, [i % 256] for i < syncs */
} ft_dvs_stream;

void ft_dvs_stream_init(ft_dvs_stream *s);
/* Restarts the time base and drops a partial word (after a device reconnect); counters stay. */
void ft_dvs_stream_restart(ft_dvs_stream *s);
/* Decodes buf[0..len) into out (room for cap events). Returns the events written; *used is the
 * bytes consumed (less than len only when out filled up: call again with the rest). */
size_t ft_dvs_stream_feed(ft_dvs_stream *s, const uint8_t *buf, size_t len, ft_event *out,
                          size_t cap, size_t *used);

#endif
