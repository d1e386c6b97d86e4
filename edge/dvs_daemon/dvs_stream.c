/* DVS128 USB byte stream parser (see dvs_stream.h). */
#include "dvs_stream.h"

#include <string.h>

void ft_dvs_stream_init(ft_dvs_stream *s) {
    memset(s, 0, sizeof *s);
    ft_dvs_decoder_init(&s->dec);
}

void ft_dvs_stream_restart(ft_dvs_stream *s) {
    ft_dvs_decoder_init(&s->dec);
    s->n_carry = 0;
}

/* One complete word; returns 1 if it produced an event in *e. */
static int word(ft_dvs_stream *s, const uint8_t *p, ft_event *e) {
    ft_dvs_word w;
    ft_dvs_event ev;
    s->words++;
    if (ft_dvs_word_decode(p, &w) != FT_OK) {
        s->bad_words++;
        return 0;
    }
    if (w.kind == FT_DVS_WRAP)
        s->wraps++;
    else if (w.kind == FT_DVS_RESET)
        s->resets++;
    if (!ft_dvs_apply(&s->dec, &w, &ev)) {
        if (w.kind == FT_DVS_SYNC) /* the bridge's sync input: a trigger pulse, at its time */
            s->sync_t[s->syncs++ % FT_DVS_STREAM_SYNCS] = (int64_t)s->dec.sync_t_us;
        return 0;
    }
    e->t = (int64_t)ev.t_us;
    e->x = ev.x;
    e->y = ev.y;
    e->p = ev.polarity;
    e->pad[0] = e->pad[1] = e->pad[2] = 0;
    s->events++;
    return 1;
}

size_t ft_dvs_stream_feed(ft_dvs_stream *s, const uint8_t *buf, size_t len, ft_event *out,
                          size_t cap, size_t *used) {
    size_t i = 0, n = 0;
    if (s->n_carry && cap > 0) { /* complete the word the last transfer cut */
        size_t take = 4 - s->n_carry < len ? 4 - s->n_carry : len;
        memcpy(s->carry + s->n_carry, buf, take);
        s->n_carry += take;
        i = take;
        if (s->n_carry < 4) {
            *used = i;
            return 0;
        }
        s->n_carry = 0;
        n += (size_t)word(s, s->carry, &out[n]);
    }
    while (i + 4 <= len && n < cap) {
        n += (size_t)word(s, buf + i, &out[n]);
        i += 4;
    }
    if (n < cap && i < len) { /* a word cut by the end of this transfer */
        memcpy(s->carry, buf + i, len - i);
        s->n_carry = len - i;
        i = len;
    }
    *used = i;
    return n;
}
