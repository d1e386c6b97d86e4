"""`flytrack edge-oak`: run an OAK camera (depthai) as a FlyTrack edge."""

from __future__ import annotations

import logging
import signal

import typer
from rich.console import Console

err_console = Console(stderr=True)


def edge_oak_command(
    host: str = typer.Option("127.0.0.1", help="The FlyTrack host's address (FEATURES and STATUS go there)."),
    port: int = typer.Option(9000, help="The host's UDP port."),
    camera_index: int = typer.Option(0, help="This camera's index in the rig (camera_index of every datagram)."),
    camera_name: str = typer.Option("oak", help="Name sent in STATUS (at most 32 bytes)."),
    device: str = typer.Option("", help="The OAK's MxId (serial); empty = the first device found."),
    kind: str = typer.Option("mono", help="mono: a mono sensor's GRAY8 frames; color: the color sensor's "
                             "luma (NV12 video output)."),
    socket_name: str = typer.Option("CAM_B", "--socket", help="Board socket of the camera: CAM_A (color on "
                                    "most OAKs), CAM_B / CAM_C (the mono pair), CAM_D."),
    resolution: str = typer.Option("400p", help="mono: 400p, 480p, 720p, 800p; color: 720p, 800p, 1080p."),
    fps: float = typer.Option(60.0, help="Sensor frame rate."),
    diff_threshold: float = typer.Option(30.0, help="Extractor: minimum absolute difference from background."),
    n_sigma: float = typer.Option(7.0, help="Extractor: minimum difference in background standard deviations."),
    alpha: float = typer.Option(0.01, help="Extractor: background running-average weight."),
    bg_update_interval: int = typer.Option(200, help="Extractor: frames between background updates."),
    truncate: bool = typer.Option(False, help="Send the 32 strongest points (TRUNCATED) instead of SPLIT."),
    reconnect_tries: int = typer.Option(5, help="Failed reconnects in a row before giving up (0: never)."),
    max_frames: int = typer.Option(0, help="Stop after this many frames (0: run until Ctrl-C)."),
) -> None:
    """Run a Luxonis OAK camera as an edge: its frames (device sequence numbers and clock) go through
    the C feature extractor and out as FEATURES, with a STATUS heartbeat every second, exactly like
    `flytrack-edge`. A lost device is reported (STATUS ERROR) and reconnected."""
    from flytrack_host.edges.features.extractor import ExtractorParams, FeatureError
    from flytrack_host.edges.oak.edge import OakEdge, OakEdgeConfig, OakEdgeError
    from flytrack_host.edges.oak.pipeline import CameraSpec, OakConfigError
    from flytrack_host.edges.oak.source import DepthaiSource, available_devices

    logging.basicConfig(level=logging.INFO, format="edge-oak: %(message)s")
    spec = CameraSpec(kind=kind, socket=socket_name, resolution=resolution, fps=fps)
    try:
        spec.check()
        found = available_devices()
        if not found or (device and device not in found):
            raise OakEdgeError(f"no OAK device{' ' + device if device else ''} found (depthai sees "
                               f"{', '.join(found) or 'none'}): "
                               "check the USB/PoE link")
        width, height = spec.size()
        params = ExtractorParams(alpha=alpha, n_sigma=n_sigma, diff_threshold=diff_threshold,
                                 bg_update_interval=bg_update_interval)
        cfg = OakEdgeConfig(host=host, port=port, camera_index=camera_index, camera_name=camera_name,
                            width=width, height=height, params=params, truncate=truncate,
                            reconnect_tries=reconnect_tries, max_frames=max_frames)
        edge = OakEdge(DepthaiSource(spec, device), cfg)
        signal.signal(signal.SIGTERM, lambda *_: edge.stop())
        try:
            n = edge.run()
        except KeyboardInterrupt:
            edge.stop()
            n = edge.frames_seen
        finally:
            edge.close()
    except (OakEdgeError, OakConfigError, FeatureError, OSError) as exc:
        err_console.print(f"[red]error[/red] {exc}", highlight=False, soft_wrap=True)
        raise typer.Exit(code=2) from None
    err_console.print(f"edge-oak: {n} frames, {edge.frames_dropped} dropped, {edge.reconnects} reconnects",
                      highlight=False)
