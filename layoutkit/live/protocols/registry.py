"""The protocol registry entry: one symmetric record per wire protocol (after trimesh's
``exchange/load.py``).

Each protocol module contributes one :class:`ProtocolEntry` (``layoutkit.PROTOCOL``,
``bitcraze.LH1_PROTOCOL``, ``bitcraze.LH2_PROTOCOL``) naming its decoder factory, its encoder (or
None when layoutkit cannot produce the stream) and how the decoder options follow from a station
set-up. :data:`layoutkit.live.protocols.PROTOCOLS` collects them; the simulator, ``fake-fpga``,
``replay`` and ``live`` dispatch through it and the CLI offers its keys as choices.
"""
from __future__ import annotations

import inspect
from dataclasses import dataclass
from typing import Callable

__all__ = ["ProtocolEntry"]


@dataclass(frozen=True)
class ProtocolEntry:
    """One wire protocol.

    name : registry key (``--protocol`` value, sidecar ``protocol``).
    decoder : factory ``decoder(n_sensors=..., **options)`` → an incremental decoder (``feed``,
        ``flush``, ``stats``; :class:`layoutkit.live.protocols.Decoder`).
    encoder : ``encoder(sweeps) -> list[bytes | None]``, the wire bytes of every simulated sweep
        (:class:`layoutkit.live.simulator.SimulatedSweeps`; None = nothing on the wire for that
        sweep, e.g. a lost frame), or None when layoutkit cannot emit this protocol.
    station_options : ``station_options(stations, n_sensors) -> dict``, the decoder options implied
        by a station set-up (rotor speed, clock); stored in a capture sidecar and passed to
        :meth:`make_decoder`.
    description : one line for ``--help`` and docs.
    """

    name: str
    decoder: Callable
    encoder: Callable | None = None
    station_options: Callable | None = None
    description: str = ""

    def options(self, stations=None, n_sensors: int | None = None) -> dict:
        """Decoder options for ``stations`` (a list of :class:`~layoutkit.lighthouse.Station`)."""
        out = {} if n_sensors is None else {"n_sensors": int(n_sensors)}
        if self.station_options is not None:
            out.update(self.station_options(list(stations or ()), n_sensors))
        return out

    def make_decoder(self, n_sensors: int, stations=None, options: dict | None = None):
        """A decoder for ``n_sensors``: options from ``stations``, overridden by ``options``.

        Options the decoder does not take (e.g. keys of another protocol in an old sidecar) are
        ignored.
        """
        kw = self.options(stations, n_sensors)
        kw.update(options or {})
        params = inspect.signature(self.decoder).parameters
        kw = {k: v for k, v in kw.items() if k != "n_sensors" and k in params}
        return self.decoder(n_sensors=n_sensors, **kw)

    def encode(self, sweeps) -> list:
        """Wire bytes per sweep (see ``encoder``); ValueError when this protocol has no encoder."""
        if self.encoder is None:
            raise ValueError(f"protocol {self.name}: layoutkit cannot emit this protocol (decode only)")
        return self.encoder(sweeps)

    def __call__(self, *args, **kwargs):
        """Back-compat: ``PROTOCOLS[name](n_sensors=...)`` builds the decoder as before."""
        return self.decoder(*args, **kwargs)
