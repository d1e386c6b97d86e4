"""Start the live outputs on a pipeline, as `flytrack run` and `flytrack demo --serve` do.

    outputs = LiveOutputs.from_options(http="127.0.0.1:8397", pose="127.0.0.1:7300")
    outputs.attach(pipe)        # before pipe.start(); the pipeline closes them when it stops
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from flytrack_host.live.pose import PoseStream, check_settings, parse_lock
from flytrack_host.live.web.server import LiveServer, parse_bind

DEFAULT_HTTP = "127.0.0.1:8397"
HTTP_HELP = ("Serve Braid's event stream (/events) and the live page on HOST:PORT; 'off' for none. "
             "Any address other than loopback needs the token printed at start.")
THUMBS_HELP = ("Ask each camera's edge for a full frame every this many seconds (CONTROL on the rig's "
               "host.control_port) for the live page's thumbnails; 0: show only images the edges send.")
POSE_HELP = "Send the VR pose stream (UDP datagrams, see flytrack_host.live.pose) to HOST:PORT."


class OutputsError(ValueError):
    """A live-output option is wrong; the message names it."""


@dataclass
class LiveOutputs:
    http: tuple[str, int] | None = None
    http_required: bool = True  # False for the default address: busy, it is skipped with a warning
    token: str | None = None
    pose: tuple[str, int] | None = None
    pose_rate_hz: float = 200.0
    pose_lead_s: float = 0.0
    pose_lock: str | int = "auto"
    pose_drop_s: float = 0.5
    thumbnails_every_s: float = 0.0  # ask each edge for a full frame this often (0: only what they send)
    server: LiveServer | None = None
    pose_stream: PoseStream | None = None
    started: list[str] = field(default_factory=list)

    @classmethod
    def from_options(cls, http: str | None = DEFAULT_HTTP, pose: str | None = None, pose_rate: float = 200.0,
                     pose_lead_ms: float = 0.0, pose_lock: str = "auto", pose_drop_s: float = 0.5,
                     token: str | None = None, thumbnails_every_s: float = 0.0) -> LiveOutputs:
        try:
            h = None if http is None or http.strip().lower() in ("off", "none", "") else parse_bind(http)
            p = None
            if pose:
                p = parse_bind(pose, default_port=7300)
                if p[1] == 0:
                    raise ValueError("the pose destination needs a port")
            lock = parse_lock(pose_lock)
            check_settings(pose_rate, pose_lead_ms / 1e3, pose_drop_s)
            if not (math.isfinite(thumbnails_every_s) and 0 <= thumbnails_every_s <= 3600):
                raise ValueError(f"--thumbnails must be 0 (off) to 3600 s, got {thumbnails_every_s}")
        except ValueError as exc:
            raise OutputsError(str(exc)) from None
        return cls(http=h, http_required=http != DEFAULT_HTTP, token=token, pose=p, pose_rate_hz=pose_rate,
                   pose_lead_s=pose_lead_ms / 1e3,
                   pose_lock=lock, pose_drop_s=pose_drop_s, thumbnails_every_s=thumbnails_every_s)

    def attach(self, pipe: Any, echo: Callable[[str], object] = print) -> None:
        """Join the pipeline's sinks and start. Raises OSError when the HTTP port cannot be bound,
        OutputsError for a bad pose setting."""
        if self.http is not None:
            server = LiveServer(self.http[0], self.http[1], token=self.token,
                                thumbnails_every_s=self.thumbnails_every_s)
            try:
                server.attach(pipe)
            except OSError as exc:
                if self.http_required:
                    raise
                # The default port is taken (another host, a second run): tracking matters more
                # than the live view, so go on without it and say so.
                line = (f"warning: live view and Braid events off: cannot listen on "
                        f"{self.http[0]}:{self.http[1]} ({exc.strerror or exc}); choose another with --http")
            else:
                self.server = server
                line = server.banner()
            self.started.append(line)
            echo(line)
        if self.pose is not None:
            try:
                self.pose_stream = PoseStream([self.pose], rate_hz=self.pose_rate_hz, lead_s=self.pose_lead_s,
                                              lock=self.pose_lock, drop_after_s=self.pose_drop_s)
            except ValueError as exc:
                raise OutputsError(str(exc)) from None
            pipe.sinks.append(self.pose_stream)
            line = (f"pose stream: {self.pose_rate_hz:g} Hz to {self.pose[0]}:{self.pose[1]}, lock "
                    f"{self.pose_lock}, lead {self.pose_lead_s * 1e3:g} ms")
            self.started.append(line)
            echo(line)
