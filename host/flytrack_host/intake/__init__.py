"""Intake: the edges' packets into the host. `receiver` takes FEATURES and STATUS datagrams off the UDP
socket and checks their sender; `sync` ties each camera frame to its trigger frame and bundles the
cameras' frames of one trigger frame for the tracker.

May import: util, protocol, rig, tracking.
"""
