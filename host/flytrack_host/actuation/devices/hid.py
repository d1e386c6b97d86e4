"""HID output reports (hidapi). No HID device can exist on this machine, so the hidapi calls sit
behind a thin seam, `HidBackend`: the real one wraps `hid.device`; the tests give their own backend
(a stand-in device that records reports), which is the only mock of this module."""

from __future__ import annotations

from typing import Protocol

from flytrack_host.actuation.devices.base import Done, Job, Output, OutputError
from flytrack_host.util import hostclock


class HidHandle(Protocol):
    def write(self, data: bytes) -> int: ...
    def close(self) -> None: ...


class HidBackend(Protocol):
    def open(self, vendor_id: int | None, product_id: int | None, path: str) -> HidHandle: ...


class HidapiBackend:
    """The real backend: hidapi's `hid.device`."""

    def open(self, vendor_id: int | None, product_id: int | None, path: str) -> HidHandle:
        import hid

        dev = hid.device()
        try:
            if path:
                dev.open_path(path.encode())
            else:
                dev.open(vendor_id, product_id)
        except (OSError, ValueError) as exc:
            what = path or f"{vendor_id:04x}:{product_id:04x}"
            raise OutputError(f"no HID device {what}: {exc}") from None
        return dev


class HidOutput(Output):
    kind = "hid"
    ack_means = "the output report write returned"

    def __init__(self, *args: object, **kw: object):
        super().__init__(*args, **kw)  # type: ignore[arg-type]
        self.backend: HidBackend = self.context.get("hid_backend") or HidapiBackend()
        self.handle: HidHandle | None = None

    def _connect(self) -> None:
        self.handle = self.backend.open(self.cfg.vendor_id, self.cfg.product_id, self.cfg.address)

    def _perform(self, job: Job) -> Done:
        if self.handle is None:
            raise OutputError("not connected")
        a = job.action
        report = bytes([a.report_id or 0]) + bytes(a.data or [])  # hidapi: first byte is the report id
        t0 = hostclock.now()
        self.written()  # the transfer may take long: the tracking thread does not wait for it
        n = self.handle.write(report)
        if n < 0:
            raise OutputError("hid write failed (device gone?)")
        return Done(t0, hostclock.now())

    def _close(self) -> None:
        if self.handle is not None:
            self.handle.close()
            self.handle = None
