/* flytrack-edge's loop for event sources (edge_dvs.c). */
#ifndef FLYTRACK_EDGE_DVS_H
#define FLYTRACK_EDGE_DVS_H

#include "config.h"

int edge_is_event_source(const char *source); /* "dvs128" or "events" */
int edge_dvs_run(edge_config *cfg);           /* the process exit code */

#endif
