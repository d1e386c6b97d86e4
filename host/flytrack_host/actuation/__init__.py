"""Closed loop: rules on the live 3D state drive the trigger firmware's outputs and lab devices.

rules.py (the TOML rules file), conditions.py (regions, speeds, distances on N objects at once),
history.py (per-object entries, cooldown, rate, arming), prediction.py (latency compensation),
engine.py (the pipeline sink and the per-device workers), devices/ (one module per kind of output),
firings.py (the recorded table), replay.py (`flytrack rules replay`).

May import: util, protocol, tracking, rig, trigger, recording.
"""
