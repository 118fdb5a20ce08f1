"""Byte sources: serial ports (any pyserial URL), capture files, and a reconnecting serial port.

Every source has ``read(max_bytes) -> bytes`` (``b""`` when nothing arrived within its timeout
or at the end of a capture), ``close()`` and ``eof`` (True only for a finished capture).
"""
from __future__ import annotations

import time
from pathlib import Path

__all__ = ["open_source", "SerialSource", "ReconnectingSerial", "is_capture"]

DEFAULT_BAUDRATE = 921600
_URL_SCHEMES = ("loop://", "socket://", "rfc2217://", "spy://", "alt://", "hwgrep://", "cp2110://")


def is_capture(url_or_path) -> bool:
    """True when ``url_or_path`` names a regular file (a capture), not a device or URL."""
    s = str(url_or_path)
    if s.startswith(_URL_SCHEMES):
        return False
    p = Path(s)
    return p.is_file()


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
        self.port = serial.serial_for_url(url, baudrate=baudrate, timeout=timeout, **kwargs)

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
    ``on_event(kind, state)`` (optional) is called on "connected" / "disconnected".
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
        self._closed = False
        self._try_open()

    @property
    def connected(self) -> bool:
        return self._src is not None

    @property
    def state(self) -> dict:
        return {"connected": self.connected, "connects": self.connects, "disconnects": self.disconnects,
                "retries": self.retries, "last_error": self.last_error, "next_retry_s": self._delay}

    @property
    def settings(self) -> dict:
        return {"url": self.url, "baudrate": self.baudrate, "timeout": self.timeout, "reconnect": True}

    def _try_open(self) -> bool:
        import serial

        try:
            self._src = self._opener()
        except (serial.SerialException, OSError, ValueError) as exc:
            self._src = None
            self.retries += 1
            self.last_error = str(exc)
            self._next_try = time.monotonic() + self._delay
            self._delay = min(self._delay * 2.0, self.backoff_max)
            return False
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
