"""Geometry shared by the tracker, the calibration, the simulator and fish: the one camera model
(`camera`: pinhole + OpenCV distortion), refraction at flat interfaces (`refraction`), and every
calibration file format FlyTrack reads and writes (`formats`: flydra XML, pymvg JSON, OpenCV YAML,
anipose TOML).

May import: util.
"""
