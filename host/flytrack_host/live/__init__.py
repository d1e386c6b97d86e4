"""Live outputs of a run: the LIVE_ESTIMATES datagram and its client (`udp`), Braid's message model
(`braid`), the VR pose stream (`pose`), starting them for a run (`launch`), and the HTTP server with
Braid's event stream, the live page and the control API (`web`).

May import: util, protocol, geometry, tracking, rig, intake.
"""
