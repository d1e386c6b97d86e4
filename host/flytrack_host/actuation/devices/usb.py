"""USB control or bulk OUT transfers (pyusb). No USB device of this kind exists on this machine, so
the pyusb calls sit behind a thin seam, `UsbBackend`: the real one uses `usb.core.find`; tests give a
stand-in device (the only mock of this module). The transfer's return is the device's
acknowledgement (a control transfer completes after its status stage)."""

from __future__ import annotations

from typing import Any, Protocol

from flytrack_host.actuation.devices.base import Done, Job, Output, OutputError
from flytrack_host.util import hostclock


class UsbHandle(Protocol):
    def ctrl_transfer(self, bmRequestType: int, bRequest: int, wValue: int, wIndex: int,  # noqa: N803
                      data_or_wLength: Any, timeout: int) -> Any: ...
    def write(self, endpoint: int, data: bytes, timeout: int) -> int: ...


class UsbBackend(Protocol):
    def open(self, vendor_id: int | None, product_id: int | None) -> UsbHandle: ...
    def close(self, handle: UsbHandle) -> None: ...


class PyusbBackend:
    """The real backend: pyusb (libusb)."""

    def open(self, vendor_id: int | None, product_id: int | None) -> UsbHandle:
        import usb.core

        try:
            dev = usb.core.find(idVendor=vendor_id, idProduct=product_id)
        except usb.core.NoBackendError as exc:
            raise OutputError(f"no libusb backend: {exc}") from None
        if dev is None:
            raise OutputError(f"no USB device {vendor_id:04x}:{product_id:04x}")
        return dev

    def close(self, handle: UsbHandle) -> None:
        import usb.util

        usb.util.dispose_resources(handle)


class UsbOutput(Output):
    kind = "usb"
    ack_means = "the control or bulk transfer completed"

    def __init__(self, *args: object, **kw: object):
        super().__init__(*args, **kw)  # type: ignore[arg-type]
        self.backend: UsbBackend = self.context.get("usb_backend") or PyusbBackend()
        self.handle: UsbHandle | None = None

    def _connect(self) -> None:
        self.handle = self.backend.open(self.cfg.vendor_id, self.cfg.product_id)

    def _perform(self, job: Job) -> Done:
        if self.handle is None:
            raise OutputError("not connected")
        a = job.action
        ms = max(1, int(self.cfg.timeout_s * 1000))
        data = bytes(a.data or [])
        t0 = hostclock.now()
        self.written()  # the transfer may take long: the tracking thread does not wait for it
        if a.endpoint is not None:
            self.handle.write(a.endpoint, data, ms)
        else:
            self.handle.ctrl_transfer(int(a.request_type or 0), int(a.request or 0), int(a.w_value or 0),
                                      int(a.w_index or 0), data, ms)
        return Done(t0, hostclock.now())

    def _close(self) -> None:
        if self.handle is not None:
            self.backend.close(self.handle)
            self.handle = None
