/* What the event-file readers' parts all use: the input buffer (ev_need), the first error
 * (ev_fail) and trigger times (ev_trigger). Both the read loop (ev_reader.c) and the per-format
 * decoders (ev_aedat.c, ev_prophesee.c) call these, and these call neither: calls go from the
 * reader to the decoders to this file, never back. */
#define _POSIX_C_SOURCE 200809L
#include <errno.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <unistd.h>

#include "ev_internal.h"

void ev_fail(ft_ev_reader *r, uint64_t off, const char *fmt, ...) {
    char msg[240];
    va_list ap;
    if (r->failed)
        return; /* the first damage is the one reported */
    va_start(ap, fmt);
    vsnprintf(msg, sizeof msg, fmt, ap);
    va_end(ap);
    snprintf(r->err, sizeof r->err, "%s: at byte %llu: %s", r->name, (unsigned long long)off, msg);
    r->err_off = (long long)off;
    r->failed = 1;
}

int ev_need(ft_ev_reader *r, size_t n) {
    if (r->end - r->start >= n)
        return 1;
    if (r->fd < 0 || r->eof)
        return 0;
    if (n > FT_EV_MAX_UNIT + 64)
        return 0;
    if (r->start > 0) { /* keep only the unconsumed bytes */
        memmove(r->buf, r->buf + r->start, r->end - r->start);
        r->data_off += r->start;
        r->end -= r->start;
        r->start = 0;
    }
    if (n > r->buf_cap) {
        size_t cap = r->buf_cap;
        while (cap < n)
            cap *= 2;
        uint8_t *nb = realloc(r->buf, cap);
        if (!nb) {
            ev_fail(r, ev_pos(r), "out of memory for a unit of %zu bytes", n);
            return 0;
        }
        r->buf = nb;
        r->data = nb;
        r->buf_cap = cap;
    }
    while (r->end - r->start < n) {
        ssize_t got = read(r->fd, r->buf + r->end, r->buf_cap - r->end);
        if (got < 0) {
            if (errno == EINTR)
                continue;
            ev_fail(r, r->data_off + r->end, "read error: %s", strerror(errno));
            return 0;
        }
        if (got == 0) {
            r->eof = 1;
            return 0;
        }
        r->end += (size_t)got;
    }
    return 1;
}

void ev_trigger(ft_ev_reader *r, int64_t t, unsigned value, unsigned channel) {
    r->info.n_triggers++;
    if (!r->keep_triggers)
        return;
    if (r->trig_n == r->trig_cap) {
        size_t cap = r->trig_cap ? 2 * r->trig_cap : 256;
        ft_ev_trigger *nt = realloc(r->trig, cap * sizeof *nt);
        if (!nt) {
            ev_fail(r, ev_pos(r), "out of memory keeping %zu trigger times", r->trig_n);
            return;
        }
        r->trig = nt;
        r->trig_cap = cap;
    }
    ft_ev_trigger *e = &r->trig[r->trig_n++];
    memset(e, 0, sizeof *e);
    e->t = t;
    e->value = (uint8_t)(value != 0);
    e->channel = (uint8_t)channel;
}
