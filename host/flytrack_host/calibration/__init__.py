"""Camera calibration: DLT, LED self-calibration with bundle adjustment, world alignment, file formats.

`flytrack_host.geometry.formats` reads and writes every calibration file format; the other modules
compute calibrations. All of them use the one camera model, `flytrack_host.geometry.camera.Camera`.

May import: util, protocol, geometry, recording, dvs.
"""
