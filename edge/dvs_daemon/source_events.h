/* Event sources of flytrack-edge: event files (libflytrack_events) and a DVS128 on USB.
 *
 * The USB side talks to libusb-1.0 only through ft_usb_ops, the seam: no DVS128 exists on the
 * build machine, so tests/test_dvs_source.c replaces it with a fake device that delivers recorded
 * byte streams in arbitrary bulk-transfer sizes and is unplugged and plugged back in;
 * ft_usb_libusb_ops is the real library. */
#ifndef FLYTRACK_EDGE_SOURCE_EVENTS_H
#define FLYTRACK_EDGE_SOURCE_EVENTS_H

#include <stddef.h>
#include <stdint.h>

#include "dvs_stream.h"
#include "flytrack/events.h"
#include "source.h"

/* DVS128 over USB (as jAER and libcaer drive it) */
#define FT_DVS128_VID 0x152A
#define FT_DVS128_PID 0x8400
#define FT_DVS128_EP_IN 0x86
#define FT_DVS128_REQ_START 0xB3
#define FT_DVS128_REQ_STOP 0xB4
#define FT_DVS128_REQ_BIASES 0xB8 /* 12 biases x 3 bytes, big-endian */
#define FT_DVS128_REQ_RESET_TS 0xBB
#define FT_DVS128_REQ_TS_MASTER 0xBE /* wValue 1 = master */
#define FT_DVS128_BIAS_BYTES 36

enum { FT_USB_OK = 0, FT_USB_TIMEOUT = -7, FT_USB_NO_DEVICE = -4, FT_USB_ERROR = -1 };

typedef struct {
    int (*init)(void **ctx);
    void (*exit)(void *ctx);
    /* The device handle (interface 0 claimed), or NULL when no such device is there. */
    void *(*open)(void *ctx, uint16_t vid, uint16_t pid);
    /* Vendor request, host to device; FT_USB_OK or an error. */
    int (*control_out)(void *h, uint8_t request, uint16_t value, const uint8_t *data, uint16_t len,
                       unsigned timeout_ms);
    /* Bulk IN; *got bytes arrived (also with FT_USB_TIMEOUT); FT_USB_NO_DEVICE when unplugged. */
    int (*bulk_in)(void *h, uint8_t ep, uint8_t *buf, int len, int *got, unsigned timeout_ms);
    void (*close)(void *h);
} ft_usb_ops;
extern const ft_usb_ops ft_usb_libusb_ops;

typedef struct ft_ev_source ft_ev_source;
struct ft_ev_source {
    /* Waits at most timeout_ms; fills out with up to cap (>= 16) events. Returns the count (0:
     * none yet), FT_SRC_END or FT_SRC_ERROR (error set). */
    long (*next)(ft_ev_source *s, ft_event *out, size_t cap, int timeout_ms);
    void (*close)(ft_ev_source *s);
    uint32_t width, height;
    uint64_t lost;     /* garbage words skipped (DVS128) */
    uint64_t triggers; /* external trigger / sync events seen */
    /* times (us, the events' time base) of the latest sync events: sync_t[i % FT_SRC_SYNC_RING]
     * for i < triggers; the caller takes them as they come (a sync may run ahead of the events
     * delivered so far) */
#define FT_SRC_SYNC_RING 256
    int64_t sync_t[FT_SRC_SYNC_RING];
    int drained; /* set by next: every event decoded so far has been delivered (so every event
                  * before the latest sync is in) */
    uint64_t reconnects; /* DVS128 plugged back in */
    int connected;       /* DVS128: 0 while unplugged */
    int state_changed;   /* set by the source when connected changes (the caller clears it) */
    int invert_polarity; /* DVS128: set to 1 for an original DVS128 (raw bit 0 = 1 is OFF) */
    char error[240];
    void *priv;
};

/* format: NULL or "auto" to detect; realtime: deliver events at their recorded pace (else as fast
 * as the reader goes). 0 or -1 with s->error set. */
int ft_ev_source_open_file(ft_ev_source *s, const char *path, const char *format, int realtime);
/* biases: 36 bytes to send, or NULL to keep the device's; reopen_ms: retry period while
 * unplugged. Fails (-1) when no DVS128 is there at the start. */
int ft_ev_source_open_dvs128(ft_ev_source *s, const ft_usb_ops *ops, const uint8_t *biases,
                             int reopen_ms);

#endif
