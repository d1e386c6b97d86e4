"""The rig file: one TOML file that describes a whole FlyTrack rig.

It names the cameras and where their feature packets come from, the trigger box, the calibration,
the tracking parameters, where recordings go, and the actuators. `load_rig` validates it with
pydantic and turns every problem into a `RigError` whose lines name the file, the field and the fix.

May import: util, protocol, tracking.
"""

from __future__ import annotations

import ipaddress
import tomllib
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from flytrack_host.protocol.trigger_link import BAUD as FLYTRACK_BAUD
from flytrack_host.tracking.params import TrackingParams


class RigError(Exception):
    """A rig file that cannot be used; `str()` is a message for the user, one problem per line."""

    def __init__(self, path: Path | str, problems: list[str]):
        self.path = Path(path)
        self.problems = problems
        super().__init__("\n".join(f"{self.path}: {p}" for p in problems))


def _check_host_port(value: str) -> str:
    host, sep, port = value.rpartition(":")
    if not sep or not host:
        raise ValueError(f"{value!r} is not HOST:PORT; write it like '127.0.0.1:7000'")
    if not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"port in {value!r} must be a number from 1 to 65535")
    return value


HostPort = Annotated[str, Field(description="HOST:PORT, e.g. 127.0.0.1:7000")]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class CameraConfig(_Strict):
    name: str = Field(min_length=1, description="Camera name, as in the calibration file.")
    index: int = Field(ge=0, lt=0xFFFF, description="camera_index carried in every feature datagram.")
    edge: str = Field(
        "127.0.0.1", description="IP address feature datagrams from this camera come from."
    )
    calibration_id: str | None = Field(
        None, description="Name of the camera in the calibration file, when it differs from `name`."
    )
    kind: Literal["frame", "dvs"] = Field(
        "frame",
        description="frame: a camera whose edge sends FEATURES per trigger frame; dvs: an event camera "
        "whose edge sends DVS_CLUSTERS per time slice (its clusters become 2D observations).",
    )

    @field_validator("edge")
    @classmethod
    def _edge_is_ip(cls, v: str) -> str:
        try:
            ipaddress.ip_address(v)
        except ValueError:
            msg = f"{v!r} is not an IP address; write the edge computer's address, e.g. '10.0.0.5'"
            raise ValueError(msg) from None
        return v

    @property
    def calib_name(self) -> str:
        return self.calibration_id or self.name


class TriggerConfig(_Strict):
    kind: Literal["flytrack", "strawlab", "software"] = Field(
        "flytrack",
        description="flytrack: FlyTrack firmware; strawlab: a strawlab triggerbox; software: no box (simulation).",
    )
    port: str = Field("/dev/ttyUSB0", description="Serial port of the trigger box.")
    fps: float = Field(100.0, gt=0, le=10000, description="Frame rate to trigger, frames per second.")
    baud: int = Field(0, ge=0, description="Serial baud rate; 0 (default): the box's own, 1000000 for the FlyTrack "
                      "firmware, 115200 for a strawlab triggerbox.")
    clock_query_interval_s: float = Field(0.5, gt=0, description="How often the host samples the device clock.")

    @model_validator(mode="after")
    def _default_baud(self) -> TriggerConfig:
        if self.baud == 0:
            self.baud = FLYTRACK_BAUD if self.kind == "flytrack" else 115_200
        return self


class HostConfig(_Strict):
    listen: HostPort = Field("0.0.0.0:7000", description="Where the host receives feature datagrams.")
    control_port: int = Field(7001, gt=0, lt=65536, description="Edge control port (host -> edge).")
    live_subscribers: list[HostPort] = Field(
        default_factory=list, description="UDP HOST:PORT addresses that receive live estimates."
    )
    sync_deadline_fraction: float = Field(
        0.5,
        gt=0,
        le=10,
        description="A frame bundle is tracked at latest this fraction of a frame period after its first packet.",
    )
    cpu_wake_latency_us: Literal["auto", "off"] | Annotated[int, Field(ge=0, le=1_000_000)] = Field(
        "auto",
        description="While the host runs, ask Linux (PM QoS, /dev/cpu_dma_latency) to keep idle CPUs at most "
        "this many microseconds from waking: a closed loop's commands and replies then do not wait for a CPU "
        "to leave a deep idle state. 'auto': 0 when rules drive actuators, else not asked; 'off': never. "
        "Costs power (idle CPUs poll); needs root or write access to the device.",
    )

    @field_validator("listen")
    @classmethod
    def _listen(cls, v: str) -> str:
        return _check_host_port(v)

    @field_validator("live_subscribers")
    @classmethod
    def _subs(cls, v: list[str]) -> list[str]:
        return [_check_host_port(s) for s in v]


class RecordingConfig(_Strict):
    folder: str = Field("recordings", description="Folder for recordings, relative to the rig file.")
    flush_interval_s: float = Field(1.0, gt=0, le=10, description="Append-only files are flushed this often.")
    part_minutes: float = Field(10.0, ge=0, description="Start a new part of the recording this often (minutes; "
                                "0: no time limit), or at part_gb, whichever comes first. Each part is finalised in "
                                "the background once closed, so stopping finalises only the last one, and a crash "
                                "damages only the part being written (docs/recordings.md).")
    part_gb: float = Field(1.0, ge=0, description="Start a new part once the part holds this many GB (0: no size "
                           "limit), or at part_minutes, whichever comes first. Both 0: one unparted recording "
                           "(stopping then finalises the whole of it, about 6-7 s per GB).")


ActuatorKind = Literal["trigger_pulse", "modbus", "can", "hid", "usb", "udp", "python"]

# What `address` means and which fields each kind needs (flytrack_host.actuation.devices).
_ADDRESS_NEEDED = {"modbus": "HOST:PORT (TCP) or a serial port (RTU)", "can": "the CAN channel, e.g. can0",
                   "udp": "HOST:PORT", "python": "module:function or path/to/file.py:function"}


class ActuatorConfig(_Strict):
    """A device the closed-loop rules drive (flytrack_host.actuation); rules name it by `name`."""

    name: str = Field(min_length=1, description="The name rules use for this device (their `output`).")
    kind: ActuatorKind = Field(description="How the actuator is driven.")
    address: str = Field("", description="HOST:PORT, serial port, CAN channel, HID path or module:function, by kind.")
    channel: int = Field(0, ge=0, description="trigger_pulse: the firmware's output channel (0 = exact pulses).")
    transport: Literal["tcp", "rtu"] = Field("tcp", description="modbus: TCP or RTU over a serial port.")
    unit: int = Field(1, ge=0, le=247, description="modbus: device (unit) id.")
    baud: int = Field(19200, gt=0, description="modbus RTU: serial speed.")
    interface: str = Field("socketcan", description="can: python-can interface (socketcan, virtual, udp_multicast...).")
    bitrate: int | None = Field(None, gt=0, description="can: bit rate, where the interface takes one.")
    vendor_id: int | None = Field(None, ge=0, le=0xFFFF, description="hid/usb: USB vendor id.")
    product_id: int | None = Field(None, ge=0, le=0xFFFF, description="hid/usb: USB product id.")
    latency_ms: float = Field(0.0, ge=0, le=10000, description="The device's own latency, added to the prediction.")
    timeout_s: float = Field(0.5, gt=0, le=60, description="Give up on one command after this long.")
    queue: int = Field(16, ge=1, le=10000, description="Commands waiting for this device at most; more are dropped.")

    @model_validator(mode="after")
    def _needs(self) -> ActuatorConfig:
        if self.kind in _ADDRESS_NEEDED and not self.address:
            raise ValueError(f"actuator {self.name!r} ({self.kind}) needs `address`: {_ADDRESS_NEEDED[self.kind]}")
        if self.kind in ("modbus", "udp") and self.transport == "tcp":
            _check_host_port(self.address)
        if self.kind in ("hid", "usb") and not self.address and (self.vendor_id is None or self.product_id is None):
            raise ValueError(f"actuator {self.name!r} ({self.kind}) needs vendor_id and product_id, or `address`")
        return self


class RigConfig(_Strict):
    name: str = Field("rig", description="A name for this rig, written into recordings.")
    calibration: str | None = Field(
        None, description="Calibration file (flydra XML or pymvg JSON), relative to the rig file."
    )
    cameras: list[CameraConfig] = Field(min_length=1, description="The cameras, one [[cameras]] table each.")
    trigger: TriggerConfig = Field(default_factory=TriggerConfig, description="The trigger box.")
    host: HostConfig = Field(default_factory=HostConfig, description="The host's network and timing settings.")
    tracking: TrackingParams = Field(default_factory=TrackingParams, description="Tracking parameters.")
    recording: RecordingConfig = Field(default_factory=RecordingConfig, description="Where and how to record.")
    actuators: list[ActuatorConfig] = Field(
        default_factory=list, description="Devices the closed-loop rules drive, one [[actuators]] table each."
    )
    rules: str | None = Field(None, description="Closed-loop rules file (TOML), relative to the rig file.")

    # Filled by load_rig: the folder relative paths are resolved against.
    base_dir: Path = Field(default=Path("."), exclude=True)

    @model_validator(mode="after")
    def _unique(self) -> RigConfig:
        seen_idx: dict[int, str] = {}
        seen_name: set[str] = set()
        for cam in self.cameras:
            if cam.index in seen_idx:
                raise ValueError(
                    f"cameras {seen_idx[cam.index]!r} and {cam.name!r} share index {cam.index}; "
                    "give every camera its own index"
                )
            if cam.name in seen_name:
                raise ValueError(f"two cameras are named {cam.name!r}; camera names must be unique")
            seen_idx[cam.index] = cam.name
            seen_name.add(cam.name)
        names = [a.name for a in self.actuators]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"actuator names {dup} are used twice; rules name actuators, so names must be unique")
        return self

    def camera_by_index(self, index: int) -> CameraConfig | None:
        for cam in self.cameras:
            if cam.index == index:
                return cam
        return None

    def resolve(self, rel: str) -> Path:
        p = Path(rel)
        return p if p.is_absolute() else self.base_dir / p

    @property
    def calibration_path(self) -> Path | None:
        return None if self.calibration is None else self.resolve(self.calibration)

    @property
    def rules_path(self) -> Path | None:
        return None if self.rules is None else self.resolve(self.rules)

    @property
    def recording_dir(self) -> Path:
        return self.resolve(self.recording.folder)


def _loc(loc: tuple) -> str:
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "(top level)"


def _fix_for(err: dict) -> str:
    kind = err.get("type", "")
    if kind == "missing":
        return "add this field"
    if kind == "extra_forbidden":
        return "remove it or check its spelling (see examples/rig.toml)"
    if kind == "literal_error":
        return "use one of the listed values"
    return "see examples/rig.toml for a valid value"


def _raw_duplicates(data: dict) -> list[str]:
    seen: dict[object, str] = {}
    out = []
    cams = data.get("cameras") if isinstance(data, dict) else None
    for i, cam in enumerate(cams if isinstance(cams, list) else []):
        if not isinstance(cam, dict) or "index" not in cam:
            continue
        name = str(cam.get("name", f"cameras[{i}]"))
        idx = cam["index"]
        if idx in seen:
            out.append(f"cameras {seen[idx]!r} and {name!r} share index {idx}; give every camera its own index")
        else:
            seen[idx] = name
    return out


def parse_rig(data: dict, path: Path | str = "<rig>") -> RigConfig:
    """Validate an already parsed TOML table."""
    path = Path(path)
    try:
        rig = RigConfig.model_validate(data)
    except ValidationError as exc:
        # Duplicate camera indices are checked on the raw table too: the model's own check runs only
        # when every field is valid, and two edges on one index is the error that costs most live.
        problems = _raw_duplicates(data)
        for err in exc.errors():
            msg = err["msg"].removeprefix("Value error, ")
            problems.append(f"{_loc(err['loc'])}: {msg} ({_fix_for(err)})")
        raise RigError(path, problems) from None
    rig.base_dir = path.parent if path.name != "<rig>" else Path(".")
    return rig


def read_toml_file(path: Path, kind: str, example: str) -> tuple[dict | None, str | None]:
    """(data, None), or (None, the problem in one line) for a missing file, a folder, bad TOML, a
    binary file or a read error. `kind` names the file ("rig", "rules"), `example` shows one."""
    if not path.exists():
        return None, f"file not found; pass the path of a {kind} TOML file (see {example})"
    if path.is_dir():
        return None, f"is a folder; pass the path of a {kind} TOML file in it (see {example})"
    try:
        return tomllib.loads(path.read_text(encoding="utf-8")), None
    except tomllib.TOMLDecodeError as exc:
        return None, f"not valid TOML: {exc}"
    except UnicodeDecodeError:
        return None, f"not a text file; a {kind} file is UTF-8 TOML"
    except OSError as exc:
        return None, f"cannot be read: {exc.strerror or exc}"


def load_rig(path: Path | str, check_files: bool = True) -> RigConfig:
    """Read and validate a rig file. Raises RigError with a readable message on any problem."""
    path = Path(path)
    data, problem = read_toml_file(path, "rig", "examples/rig.toml")
    if data is None:
        raise RigError(path, [problem or "unreadable"])
    rig = parse_rig(data, path)
    if check_files and rig.calibration_path is not None and not rig.calibration_path.exists():
        raise RigError(
            path,
            [f"calibration: file {rig.calibration_path} does not exist (fix the path or run `flytrack calibrate`)"],
        )
    if check_files and rig.rules_path is not None and not rig.rules_path.exists():
        raise RigError(path, [f"rules: file {rig.rules_path} does not exist (fix the path, or remove `rules`)"])
    return rig
