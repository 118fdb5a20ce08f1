"""Byte sources: serial ports (any pyserial URL), capture files, and a reconnecting serial port.

Every source has ``read(max_bytes) -> bytes`` (``b""`` when nothing arrived within its timeout
or at the end of a capture), ``close()`` and ``eof`` (True only for a finished capture).
"""
from __future__ import annotations

import os
import stat as stat_mod
import time
from dataclasses import dataclass
from pathlib import Path

__all__ = ["open_source", "SerialSource", "ReconnectingSerial", "is_capture", "DeviceIdentity", "device_identity",
           "same_device"]

DEFAULT_BAUDRATE = 921600
_URL_SCHEMES = ("loop://", "socket://", "rfc2217://", "spy://", "alt://", "hwgrep://", "cp2110://")


def is_capture(url_or_path) -> bool:
    """True when ``url_or_path`` names a regular file (a capture), not a device or URL."""
    s = str(url_or_path)
    if s.startswith(_URL_SCHEMES):
        return False
    p = Path(s)
    return p.is_file()


@dataclass(frozen=True)
class DeviceIdentity:
    """What the OS says about the device behind a path, to recognise it after a reconnect.

    path : the path as given (may be a symlink); target : where it leads (``os.path.realpath``).
    node : (st_dev, st_ino, st_rdev, st_ctime_ns) of the device node — a node made anew (a pty
    number given to another program, udev re-creating ``/dev/ttyUSB0``) has a new ctime even when
    its number is the same. link : (st_ino, st_ctime_ns) of the symlink itself when ``path`` is
    one (a stable name whose owner re-points it on replug, ``fake-fpga --link``), else None.
    hardware : USB ``idVendor:idProduct:serial`` from sysfs when the OS gives one, else None.
    """

    path: str
    target: str
    node: tuple
    link: tuple | None
    hardware: str | None

    def describe(self) -> str:
        hw = f", USB {self.hardware}" if self.hardware else ""
        return f"{self.target} (device {os.major(self.node[2])}:{os.minor(self.node[2])}{hw})"


def _usb_serial(rdev: int) -> str | None:
    """``idVendor:idProduct:serial`` of the USB device behind a character device, from sysfs."""
    d = Path(f"/sys/dev/char/{os.major(rdev)}:{os.minor(rdev)}")
    try:
        d = d.resolve(strict=True)
    except OSError:
        return None
    for up in [d, *d.parents][:8]:
        f = up / "serial"
        if f.is_file() and (up / "idVendor").is_file():
            try:
                return ":".join((up / n).read_text().strip() for n in ("idVendor", "idProduct", "serial"))
            except OSError:
                return None
    return None


def device_identity(url: str) -> DeviceIdentity | None:
    """The :class:`DeviceIdentity` of a device path, or None for a URL (``socket://``, ``loop://``)
    or a path that does not lead to a device now (raises nothing)."""
    if "://" in url:
        return None
    try:
        st = os.stat(url)
        lst = os.lstat(url)
    except OSError:
        return None
    link = (lst.st_ino, lst.st_ctime_ns) if stat_mod.S_ISLNK(lst.st_mode) else None
    hw = _usb_serial(st.st_rdev) if stat_mod.S_ISCHR(st.st_mode) else None
    return DeviceIdentity(url, os.path.realpath(url), (st.st_dev, st.st_ino, st.st_rdev, st.st_ctime_ns), link, hw)


def same_device(first: DeviceIdentity | None, now: DeviceIdentity | None) -> tuple[bool, str]:
    """May a reconnecting reader that first opened ``first`` read ``now``? → (ok, reason).

    Same USB serial number (when the OS gives one) → the same board, wherever it was enumerated.
    Otherwise the very same device node (same numbers and creation time), or a symlink that its
    owner has re-made since (a replug announced through the stable name). Anything else — the
    path (or an unchanged symlink) now leading to a node made anew, e.g. a pty number the system
    gave to another program after the board's simulator was killed — is refused.
    """
    if first is None or now is None:
        return True, "no device identity from the OS (URL)"
    if first.hardware or now.hardware:
        ok = first.hardware == now.hardware
        return ok, ("same USB device" if ok else f"another USB device ({now.hardware} instead of {first.hardware})")
    if now.node == first.node:
        return True, "same device node"
    if first.link is not None and now.link is not None and now.link != first.link:
        return True, f"{first.path} was re-made by its owner (replug) → {now.target}"
    return False, (f"{now.path} now leads to {now.describe()}, a device made after the one first opened "
                   f"({first.describe()}); refusing to read another device's bytes into this run")


class SerialSource:
    """A pyserial port opened with ``serial.serial_for_url``; ``read`` returns what has arrived.

    ``read`` waits up to ``timeout`` s for the first byte, then takes whatever else is already
    waiting (up to ``max_bytes``). A port failure raises only from a read that took no byte:
    when it fails after the first byte, that byte is returned and the next call raises.
    """

    eof = False

    def __init__(self, url: str, *, baudrate: int = DEFAULT_BAUDRATE, timeout: float = 0.1, **kwargs):
        import serial

        self.url = url
        self.baudrate = baudrate
        self.timeout = timeout
        if "://" not in url:  # a device path: take it exclusively (flock), so that two readers
            kwargs.setdefault("exclusive", True)  # never split one device's bytes between them
        self.identity = device_identity(url)
        self.port = serial.serial_for_url(url, baudrate=baudrate, timeout=timeout, **kwargs)
        fd = getattr(self.port, "fd", None)
        if self.identity is not None and isinstance(fd, int):  # the node we looked at is the one we opened
            st = os.fstat(fd)
            if (st.st_dev, st.st_ino, st.st_rdev) != self.identity.node[:3]:
                self.port.close()
                raise serial.SerialException(f"{url}: the device changed while it was being opened")

    def read(self, max_bytes: int = 65536) -> bytes:
        first = self.port.read(1)
        if not first:
            return b""
        try:
            waiting = self.port.in_waiting
            if waiting and max_bytes > 1:
                return first + self.port.read(min(waiting, max_bytes - 1))
        except Exception:  # noqa: BLE001 - the port failed after `first` was taken: hand it over;
            pass  # the next read raises again and the caller sees the disconnect then
        return first

    def close(self) -> None:
        try:
            self.port.close()
        except Exception:  # noqa: BLE001 - closing a dead port
            pass

    @property
    def settings(self) -> dict:
        return {"url": self.url, "baudrate": self.baudrate, "timeout": self.timeout}


class ReconnectingSerial:
    """A serial source that survives unplug/replug: reconnects with exponential back-off.

    url : device path, pty path (or a stable symlink to it), ``socket://host:port``, ...
    backoff : first retry delay (s), doubled after each failed attempt up to ``backoff_max``.
    ``read`` never raises on port errors (``serial.SerialException``, ``OSError``): it marks the
    port disconnected and returns ``b""``; every byte returned before is the caller's (nothing
    read is ever dropped). ``state`` reports connected, connects, disconnects, retries, last_error.
    ``on_event(kind, state)`` (optional) is called on "connected" / "disconnected" / "refused".

    A reconnect reads only the device first opened (:func:`same_device`): same path and, where the
    OS gives one, the same device identity (USB serial; else the same node, or a symlink re-made by
    its owner). A path that now leads to another device (a pty number reused by another program
    after the simulator was SIGKILLed) is refused: no byte is read from it; ``refusals`` counts
    these attempts and ``last_error`` says why; the reader keeps waiting for the real device.
    """

    eof = False

    def __init__(self, url: str, *, baudrate: int = DEFAULT_BAUDRATE, timeout: float = 0.1,
                 backoff: float = 0.05, backoff_max: float = 2.0, on_event=None, opener=None):
        self.url = url
        self.baudrate = baudrate
        self.timeout = float(timeout)
        self.backoff0 = float(backoff)
        self.backoff_max = float(backoff_max)
        self.on_event = on_event
        self._opener = opener or (lambda: SerialSource(url, baudrate=baudrate, timeout=timeout))
        self._src = None
        self._delay = self.backoff0
        self._next_try = 0.0
        self.connects = 0
        self.disconnects = 0
        self.retries = 0
        self.last_error = ""
        self.refusals = 0
        self.last_refusal = ""
        self.identity = None  # of the device first opened (updated on an accepted replug)
        self._closed = False
        self._try_open()

    @property
    def connected(self) -> bool:
        return self._src is not None

    @property
    def state(self) -> dict:
        return {"connected": self.connected, "connects": self.connects, "disconnects": self.disconnects,
                "retries": self.retries, "refusals": self.refusals, "last_refusal": self.last_refusal,
                "last_error": self.last_error,
                "next_retry_s": self._delay,
                "device": None if self.identity is None else self.identity.describe()}

    @property
    def settings(self) -> dict:
        return {"url": self.url, "baudrate": self.baudrate, "timeout": self.timeout, "reconnect": True}

    def _try_open(self) -> bool:
        import serial

        def failed(message: str) -> bool:
            self._src = None
            self.retries += 1
            self.last_error = message
            self._next_try = time.monotonic() + self._delay
            self._delay = min(self._delay * 2.0, self.backoff_max)
            return False

        if self.identity is not None:  # a reconnect: only to the device first opened
            ok, why = same_device(self.identity, device_identity(self.url))
            if not ok:
                self.refusals += 1
                first = self.last_refusal != why
                self.last_refusal = why
                failed(why)
                if first:
                    self._emit("refused")
                return False
        try:
            self._src = self._opener()
        except (serial.SerialException, OSError, ValueError) as exc:
            return failed(str(exc))
        ident = getattr(self._src, "identity", None)
        if self.identity is not None and ident is not None:
            ok, why = same_device(self.identity, ident)  # what was opened (fstat-checked), not just looked at
            if not ok:
                self._src.close()
                self.refusals += 1
                self.last_refusal = why
                return failed(why)
        if ident is not None:
            self.identity = ident
        self.connects += 1
        self._delay = self.backoff0
        self._emit("connected")
        return True

    def _emit(self, kind: str) -> None:
        if self.on_event is not None:
            self.on_event(kind, self.state)

    def read(self, max_bytes: int = 65536) -> bytes:
        import serial

        if self._closed:
            return b""
        if self._src is None:
            wait = self._next_try - time.monotonic()
            if wait > 0:
                time.sleep(min(wait, self.timeout))
                return b""
            if not self._try_open():
                return b""
        try:
            return self._src.read(max_bytes)
        except (serial.SerialException, OSError) as exc:
            self._src.close()
            self._src = None
            self.disconnects += 1
            self.last_error = str(exc)
            self._next_try = time.monotonic() + self._delay
            self._emit("disconnected")
            return b""

    def close(self) -> None:
        self._closed = True
        if self._src is not None:
            self._src.close()
            self._src = None


def open_source(url_or_path, *, baudrate: int = DEFAULT_BAUDRATE, timeout: float = 0.1,
                reconnect: bool = False, realtime: bool = False, **kwargs):
    """Open a byte source.

    A regular file → :class:`layoutkit.live.capture.CaptureReader` (``realtime`` replays the
    recorded timing). Anything else (device path, pty, ``loop://``, ``socket://host:port``) →
    :class:`SerialSource`, or :class:`ReconnectingSerial` with ``reconnect=True``.
    Raises ValueError with the port name when a serial port cannot be opened (without reconnect).
    """
    if is_capture(url_or_path):
        from .capture import CaptureReader

        return CaptureReader(url_or_path, realtime=realtime)
    url = str(url_or_path)
    if reconnect:
        return ReconnectingSerial(url, baudrate=baudrate, timeout=timeout, **kwargs)
    import serial

    try:
        return SerialSource(url, baudrate=baudrate, timeout=timeout)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise ValueError(f"{url}: cannot open serial port ({exc})") from None
