"""Serial frame protocols: a registry of symmetric entries (decoder, encoder, options).

``PROTOCOLS[name]`` is a :class:`~layoutkit.live.protocols.registry.ProtocolEntry`; each protocol
module contributes its own (``layoutkit.PROTOCOL``, ``bitcraze.LH1_PROTOCOL``,
``bitcraze.LH2_PROTOCOL``). ``dec = protocol_entry(name).make_decoder(n_sensors, stations)``;
``dec.feed(data) -> list[SweepMeasurement]`` (any chunking, never raises), ``dec.flush()``,
``dec.stats -> DecodeStats``; ``protocol_entry(name).encode(sweeps)`` gives the wire bytes of
simulated sweeps. ``get_protocol(name)`` is the decoder factory (old entry point).
Names: ``"layoutkit"`` (docs/protocol.md), ``"bitcraze-lh1"``, ``"bitcraze-lh2"`` (Bitcraze
Lighthouse deck UART stream, docs/live-io.md).
"""
from __future__ import annotations

from typing import Protocol, runtime_checkable

from ..frames import DecodeStats, SweepMeasurement
from . import bitcraze, layoutkit
from .registry import ProtocolEntry

__all__ = ["Decoder", "ProtocolEntry", "PROTOCOLS", "ENCODERS", "protocol_entry", "get_protocol"]


@runtime_checkable
class Decoder(Protocol):
    """What every protocol decoder provides."""

    stats: DecodeStats

    def feed(self, data: bytes) -> list[SweepMeasurement]: ...

    def flush(self) -> list[SweepMeasurement]: ...


#: Registered protocols by name (the ``--protocol`` choices).
PROTOCOLS: dict[str, ProtocolEntry] = {e.name: e for e in (layoutkit.PROTOCOL, bitcraze.LH1_PROTOCOL,
                                                           bitcraze.LH2_PROTOCOL)}
#: The protocols layoutkit can also emit (simulator, ``fake-fpga --protocol`` choices).
ENCODERS: dict[str, ProtocolEntry] = {k: e for k, e in PROTOCOLS.items() if e.encoder is not None}


def protocol_entry(name: str) -> ProtocolEntry:
    """The entry registered under ``name``; ValueError listing the known names otherwise."""
    try:
        return PROTOCOLS[name]
    except KeyError:
        raise ValueError(f"protocol: expected one of {sorted(PROTOCOLS)}, got {name!r}") from None


def get_protocol(name: str):
    """The decoder factory registered under ``name`` (``get_protocol(name)(n_sensors=...)``)."""
    return protocol_entry(name).decoder
