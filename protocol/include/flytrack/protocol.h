/* FlyTrack wire protocol, the whole C codec (protocol/SPEC.md). */
#ifndef FLYTRACK_PROTOCOL_H
#define FLYTRACK_PROTOCOL_H

#include "wire.h"
#include "trigger_link.h"
#include "udp.h"
#include "dvs.h"

#endif /* FLYTRACK_PROTOCOL_H */
