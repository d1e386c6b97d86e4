"""A rig camera of kind "dvs": the receiver takes its DVS_CLUSTERS over a real UDP socket, counts them
and its STATUS figures; the rig file says which cameras are event cameras."""

from __future__ import annotations

import socket
import time

import numpy as np
import pytest

from flytrack_host.intake.receiver import DvsSlice, Receiver
from flytrack_host.protocol import DvsClusters
from flytrack_host.protocol.udp import CLUSTER_DTYPE, encode
from flytrack_host.rig import RigError, parse_rig


def _rig(kind: str = "dvs"):
    return parse_rig({
        "name": "mixed", "trigger": {"kind": "software", "fps": 100.0},
        "host": {"listen": "127.0.0.1:7000"},
        "cameras": [{"name": "cam0", "index": 0, "edge": "127.0.0.1"},
                    {"name": "dvs1", "index": 1, "edge": "127.0.0.1", "kind": kind}],
    })


def test_rig_kind_is_checked():
    rig = _rig()
    assert [c.kind for c in rig.cameras] == ["frame", "dvs"]
    with pytest.raises(RigError, match="kind"):
        _rig("thermal")


def test_receiver_takes_dvs_clusters_over_udp():
    rx = Receiver(_rig(), bind="127.0.0.1:0")
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        for k in range(20):
            c = np.zeros(2, CLUSTER_DTYPE)
            c["x"], c["y"], c["size"], c["mass"] = [10.0 + k, 50.0], [20.0, 30.0], 4.0, 8.0
            msg = DvsClusters(camera_index=1, seq=k, t_start_us=k * 1000, t_end_us=k * 1000 + 999, clusters=c)
            tx.sendto(encode(msg), rx.address)
        got: list = []
        end = time.monotonic() + 5.0
        while len([g for g in got if isinstance(g, DvsSlice)]) < 20 and time.monotonic() < end:
            got += rx.receive(0.05)
        slices = [g for g in got if isinstance(g, DvsSlice)]
        assert [s.msg.seq for s in slices] == list(range(20))
        assert float(slices[3].msg.clusters["x"][0]) == pytest.approx(13.0)
        st = rx.stats.cameras[1]
        assert st.dvs_slices == 20 and st.dvs_clusters == 40 and st.lost == 0
    finally:
        tx.close()
        rx.close()
