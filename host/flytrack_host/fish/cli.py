"""`flytrack fish ...`: offline 3D shape tracking of fish (seed 004): `track` videos, `demo` on a synthetic school."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import typer
from numpy.typing import NDArray
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

app = typer.Typer(help="Fish: offline 3D shape tracking of schooling fish (seed 004).", no_args_is_help=True)
console = Console()
err = Console(stderr=True)


class VideoError(ValueError):
    """A video that cannot be used, said in one line."""


def _fail(msg: str) -> typer.Exit:
    err.print(f"[red]error:[/red] {msg}", highlight=False, soft_wrap=True)
    return typer.Exit(code=2)


class Videos:
    """Synchronised grey frames from several videos (OpenCV). The first video sets the frame rate; a video at
    another rate is read at the nearest frame in time; all stop at the shortest."""

    def __init__(self, paths: list[Path], warn: list[str]) -> None:
        self.paths = paths
        self.caps = []
        self.fps = []
        self.counts = []
        for p in paths:
            if not p.is_file():
                raise VideoError(f"{p}: no such video file")
            cap = cv2.VideoCapture(str(p))
            if not cap.isOpened():
                raise VideoError(f"{p}: OpenCV cannot open this video (codec or format not supported)")
            fps = cap.get(cv2.CAP_PROP_FPS) or 0.0
            n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
            if fps <= 0 or n <= 0:
                raise VideoError(f"{p}: the video reports no frame rate or no frames")
            self.caps.append(cap)
            self.fps.append(float(fps))
            self.counts.append(n)
        base = self.fps[0]
        for p, f in zip(paths[1:], self.fps[1:], strict=True):
            if abs(f - base) > 1e-3 * base:
                warn.append(f"{p.name} runs at {f:g} fps, {paths[0].name} at {base:g} fps: each frame of "
                            f"{paths[0].name} is paired with the nearest frame in time of {p.name}")
        # frames of the first video that every video covers
        self.length = min(int(np.floor((n - 1) * base / f)) + 1 for n, f in zip(self.counts, self.fps, strict=True))
        if len(set(self.counts)) > 1 and len(set(self.fps)) == 1:
            warn.append("videos of different lengths (" + ", ".join(f"{p.name} {n}" for p, n in
                        zip(paths, self.counts, strict=True)) + f" frames): tracking the first {self.length}")

    def _read(self, c: int, index: int, pos: list[int]) -> NDArray[np.uint8]:
        cap = self.caps[c]
        if index != pos[c]:
            cap.set(cv2.CAP_PROP_POS_FRAMES, index)
            pos[c] = index
        ok, img = cap.read()
        if not ok or img is None:
            raise VideoError(f"{self.paths[c]}: cannot read frame {index}")
        pos[c] += 1
        return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img

    def frames(self) -> Iterator[list[NDArray[np.uint8]]]:
        pos = [0] * len(self.caps)
        for cap in self.caps:
            cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
        for k in range(self.length):
            yield [self._read(c, int(round(k * self.fps[c] / self.fps[0])), pos) for c in range(len(self.caps))]

    def median_background(self, n: int = 25) -> list[NDArray[np.uint8]]:
        """B_0 per camera: the per-pixel median of `n` frames spread over the video (moving fish vanish)."""
        pos = [-1] * len(self.caps)
        idx = np.unique(np.linspace(0, self.length - 1, min(n, self.length)).astype(int))
        out = []
        for c in range(len(self.caps)):
            stack = [self._read(c, int(round(k * self.fps[c] / self.fps[0])), pos) for k in idx]
            out.append(np.median(np.stack(stack), axis=0).astype(np.uint8))
        return out


@app.command("track")
def track_command(
    videos: list[Path] = typer.Argument(..., help="Synchronised videos: the top view first, then the side "
                                        "view used to build the fish models, then any more views."),
    calibration: Path = typer.Option(..., "--calibration", "-c", help="Calibration file (flydra XML, pymvg "
                                     "JSON, OpenCV YAML, anipose TOML)."),
    cameras: str = typer.Option("", help="Calibration camera names in the order of the videos, comma-separated "
                                "(default: the video file names without extension)."),
    out: Path = typer.Option(Path("fish_tracks.h5"), "--out", "-o", help="HDF5 file to write."),
    plots: Path | None = typer.Option(None, help="Folder for the plots (seed's Figures 5, 9, 11)."),
    background_frames: int = typer.Option(0, help="Fish-free frames at the start of every video for the "
                                           "background (0: median of frames spread over the video)."),
    fish: int | None = typer.Option(None, help="Number of fish: stop making models at N (default: each fish "
                                    "that comes into clear view in the top and side views gets a model)."),
    zmin: float = typer.Option(0.0, help="Lowest height (m) a fish can be at, in the calibration's frame."),
    zmax: float = typer.Option(0.4, help="Highest height (m) a fish can be at."),
    sa_levels: int = typer.Option(6, help="Simulated-annealing temperature levels per fish and frame."),
    polish_iterations: int = typer.Option(15, help="Least-squares polish evaluations per fish and frame."),
) -> None:
    """Track fish shapes in 3D from a top and a side video; write position, heading, midline parameters,
    cross-sections, curvature and covariance per fish per frame to HDF5."""
    from flytrack_host.fish.fit import FitConfig
    from flytrack_host.fish.io import write_tracks
    from flytrack_host.fish.pipeline import TrackingError, track
    from flytrack_host.fish.tracker import TrackerConfig
    from flytrack_host.fish.views import views_from_calibration
    from flytrack_host.geometry.formats import CalibrationFormatError, load_calibration

    if len(videos) < 2:
        raise _fail("give at least two videos: the top view, then a side view")
    try:
        cams = load_calibration(calibration)
    except (CalibrationFormatError, OSError) as exc:
        raise _fail(str(exc)) from None
    names = [n.strip() for n in cameras.split(",") if n.strip()] if cameras else [v.stem for v in videos]
    if len(names) != len(videos):
        raise _fail(f"{len(names)} camera names for {len(videos)} videos")
    try:
        views = views_from_calibration(cams, names)
    except KeyError as exc:
        raise _fail(str(exc.args[0])) from None
    warn: list[str] = []
    try:
        vids = Videos(videos, warn)
    except VideoError as exc:
        raise _fail(str(exc)) from None
    for w in warn:
        err.print(f"[yellow]warning:[/yellow] {w}", highlight=False, soft_wrap=True)
    bg = None if background_frames > 0 else vids.median_background()
    n_track = vids.length - background_frames
    try:
        with Progress(TextColumn("tracking"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                      console=err, transient=True) as bar:
            task = bar.add_task("frames", total=n_track)
            res = track(vids.frames(), views, vids.fps[0], n_background=background_frames, background=bg,
                        n_fish=fish, zrange=(zmin, zmax), progress=lambda n: bar.advance(task, n),
                        cfg=TrackerConfig(fit=FitConfig(max_levels=sa_levels, qn_maxiter=polish_iterations)),
                        log=lambda m: err.print(f"[yellow]note:[/yellow] {m}", highlight=False))
    except (TrackingError, VideoError) as exc:
        raise _fail(str(exc)) from None
    write_tracks(out, res, names)
    fish_frames = int(np.sum(np.isfinite(res.smoothed[:, :, 0])))  # from each fish's model frame on
    console.print(f"{res.n_fish} fish tracked over {res.smoothed.shape[0]} frames "
                  f"({fish_frames / res.seconds:.1f} fish-frames/s) -> {out}", highlight=False)
    if plots is not None:
        from flytrack_host.fish.plots import write_plots

        for p in write_plots(plots, res, views[:2]):
            console.print(f"plot {p}", highlight=False)


@app.command("demo")
def demo_command(
    fish: int = typer.Option(4, "--fish", help="Fish in the synthetic school (1, 2, 4 or 8 are the issue's cases)."),
    frames: int = typer.Option(200, help="Frames to track (250 fps)."),
    seed: int = typer.Option(0, help="Random seed of the school and the sensor noise."),
    json_path: Path | None = typer.Option(None, "--json", help="Write the scored figures as JSON."),
    out: Path | None = typer.Option(None, help="Folder for tracks.h5 and the plots (Figures 5, 9, 11)."),
    small: bool = typer.Option(False, help="Half-size images (quicker; the figures are then at that scale)."),
    water: float | None = typer.Option(None, help="Fill the tank (refractive index, e.g. 1.333): the cameras "
                                       "look through the water surface and the tank walls (shared refraction "
                                       "model, as Braid's <water>)."),
    blas_threads: int = typer.Option(1, help="BLAS threads while tracking (0: the BLAS library's default). "
                                     "The speed is quoted on one; more only spin on the fit's small matrices "
                                     "and add CPU time."),
) -> None:
    """Render a synthetic school in a 0.61 x 0.30 x 0.40 m tank (top camera 1280x1024, side and validation
    cameras 512x384, 250 fps, sensor noise), track it and score it against the ground truth."""
    from flytrack_host.fish.demo import GOALS, goals_met, run_demo

    if fish < 1 or fish > 12:
        raise _fail("--fish must be between 1 and 12")
    if frames < 20:
        raise _fail("--frames must be at least 20")
    top = (640, 512) if small else (1280, 1024)
    side = (256, 192) if small else (512, 384)
    if blas_threads < 0:
        raise _fail("--blas-threads must be 0 (the library's default) or more")
    s = run_demo(fish, frames, seed, top, side, out=out, progress=True, water=water,
                 blas_threads=blas_threads or None)
    console.print(f"fish {s['fish']}, frames {s['frames']}, occluded fish-frames {s['occluded_fish_frames']} "
                  f"(largest group {s['max_occlusion_group']})", highlight=False)
    late = [p for p in s["per_fish"] if p["not_yet_modelled_frames"] > 0]
    when = (" (" + ", ".join(f"fish {p['truth_fish']} at frame {p['model_frame']}" for p in late) + ")") if late else ""
    console.print(f"modelled {s['fish']} of {s['fish_in_school']} fish, {len(late)} after the first frame{when}; "
                  f"scored from each fish's model frame: {s['fish_frames']} fish-frames, "
                  f"{s['not_yet_modelled_fish_frames']} not yet modelled (not errors)", highlight=False)
    if s["never_modelled_fish"]:
        console.print(f"never modelled (never in clear view): fish {s['never_modelled_fish']}", highlight=False)
    console.print(f"midline error, top view: mean {s['midline_mean_px']:.2f} px, max {s['midline_max_px']:.2f} px",
                  highlight=False)
    console.print(f"head position error: mean {s['head_mm_mean']:.2f} mm, max {s['head_mm_max']:.2f} mm",
                  highlight=False)
    console.print(f"heading error: mean {s['heading_deg_mean']:.2f} deg, max {s['heading_deg_max']:.2f} deg",
                  highlight=False)
    console.print(f"total curvature error: mean {s['curvature_error_mean_per_m']:.2f} 1/m "
                  f"(mean total curvature {s['curvature_total_mean_per_m']:.2f} 1/m)", highlight=False)
    console.print(f"association errors: {s['association_errors']}", highlight=False)
    console.print(f"validation camera midline error: mean {s['validation_midline_mean_px']:.2f} px, "
                  f"max {s['validation_midline_max_px']:.2f} px", highlight=False)
    threads = f"{blas_threads} BLAS thread{'s' if blas_threads != 1 else ''}" if blas_threads else \
        "the BLAS library's default threads"
    console.print(f"speed: {s['fish_frames_per_cpu_s']:.1f} fish-frames per CPU second, {threads} "
                  f"({s['fish_frames_per_s']:.1f} per wall second on this shared machine)", highlight=False)
    for st in s["fast_starts"]:
        console.print(f"{st['kind']} of fish {st['fish']} at frame {st['onset_frame']}: detected "
                      f"{st['detected_kind']} at {st['detected_onset']}", highlight=False)
    met = goals_met(s)
    for k, v in met.items():
        console.print(f"  [{'green' if v else 'red'}]{'met' if v else 'NOT met'}[/] {k}", highlight=False)
    console.print(f"goals met: {sum(met.values())}/{len(met)}", highlight=False)
    s["goals"] = GOALS
    s["goals_met"] = met
    if json_path is not None:
        json_path.write_text(json.dumps(s, indent=2))
