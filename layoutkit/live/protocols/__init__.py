"""Serial frame protocols: a registry of incremental decoders.

``dec = get_protocol(name)(n_sensors=..., **options)``; ``dec.feed(data) -> list[SweepMeasurement]``
(any chunking, never raises), ``dec.flush()``, ``dec.stats -> DecodeStats``.
Names: ``"layoutkit"`` (default, docs/protocol.md), ``"bitcraze-lh1"``, ``"bitcraze-lh2"``
(Bitcraze Lighthouse deck UART stream, docs/live-io.md).
"""
from __future__ import annotations

from typing import Protocol, runtime_checkable

from ..frames import DecodeStats, SweepMeasurement
from .bitcraze import BitcrazeLh1Decoder, BitcrazeLh2Decoder
from .layoutkit import LayoutkitDecoder

__all__ = ["Decoder", "PROTOCOLS", "DEFAULT_PROTOCOL", "get_protocol"]


@runtime_checkable
class Decoder(Protocol):
    """What every protocol decoder provides."""

    stats: DecodeStats

    def feed(self, data: bytes) -> list[SweepMeasurement]: ...

    def flush(self) -> list[SweepMeasurement]: ...


PROTOCOLS: dict[str, type] = {
    "layoutkit": LayoutkitDecoder,
    "bitcraze-lh1": BitcrazeLh1Decoder,
    "bitcraze-lh2": BitcrazeLh2Decoder,
}
DEFAULT_PROTOCOL = "layoutkit"


def get_protocol(name: str) -> type:
    """The decoder class registered under ``name``; ValueError listing the known names otherwise."""
    try:
        return PROTOCOLS[name]
    except KeyError:
        raise ValueError(f"protocol: expected one of {sorted(PROTOCOLS)}, got {name!r}") from None
