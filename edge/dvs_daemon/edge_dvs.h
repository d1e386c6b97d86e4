/* flytrack-edge's loop for event sources (edge_dvs.c). */
#ifndef FLYTRACK_EDGE_DVS_H
#define FLYTRACK_EDGE_DVS_H

#include "config.h"
#include "source_events.h"

int edge_is_event_source(const char *source); /* "dvs128" or "events" */
/* Runs until the source ends, fails, or SIGINT/SIGTERM/edge_dvs_stop(); returns the exit code.
 * usb: the USB layer for --source dvs128 (&ft_usb_libusb_ops; tests pass a fake device). */
int edge_dvs_run(edge_config *cfg, const ft_usb_ops *usb);
void edge_dvs_stop(void);

#endif
