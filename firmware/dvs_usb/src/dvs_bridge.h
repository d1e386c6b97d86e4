/* DVS USB bridge: vendor requests (the DVS128's, so existing host software can drive it, plus one
 * FlyTrack status request) and the status reply layout. Word format: protocol/SPEC.md section 2. */
#ifndef DVS_BRIDGE_H
#define DVS_BRIDGE_H

#define DVS_VR_START 0xB3       /* start streaming: timestamps reset (RESET word first) */
#define DVS_VR_STOP 0xB4        /* stop streaming; what is buffered is still sent */
#define DVS_VR_BIASES 0xB8      /* OUT, 36 bytes: 12 biases x 24 bits, shifted out MSB first */
#define DVS_VR_RESET_TS 0xBB    /* zero the timestamp counter now (RESET word) */
#define DVS_VR_RESET_ARRAY 0xBD /* pulse the sensor's pixel-array reset */
#define DVS_VR_TS_MASTER 0xBE   /* wValue 1: master (own clock), 0: slave (zeroed at next sync) */
#define DVS_VR_FT_STATUS 0xC8   /* IN, FlyTrack: DVS_STATUS_SIZE bytes, see below */

#define DVS_BIAS_BYTES 36
#define DVS_EP_IN 0x86

/* Status reply, little-endian:
 *   u32 overflow    events dropped because the FIFO was full (each dropped whole: no partial word)
 *   u32 sync_events sync words emitted
 *   u32 sync_missed sync pulses not recorded (two pulses before the loop took the first, or the
 *                   FIFO full to its last word)
 *   u32 clamped     sync words sent with ts 0 because a WRAP word had gone out before them
 *   u16 fifo_max    most words the FIFO ever held
 *   u8  running, u8 master */
#define DVS_STATUS_SIZE 20

#endif /* DVS_BRIDGE_H */
