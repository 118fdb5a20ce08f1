"""Crazyflie lighthouse system configuration (YAML): read and written here, nowhere else.

The file cflib and the Crazyflie client save (``type: lighthouse_system_configuration``,
``version: "1"``)::

    systemType: 2                      # 1 = Lighthouse 1 (LH1), 2 = Lighthouse 2 (LH2)
    geos:   {id: {origin: [x, y, z], rotation: [[...], [...], [...]]}}     # Crazyflie world frame, m
    calibs: {id: {uid: int, sweeps: [{phase, tilt, curve, gibmag, gibphase, ogeemag, ogeephase}] * 2}}

``geos`` rotations are in the Bitcraze station convention (x forward); layoutkit's station frame
has z = boresight (design §2), so ``Station.rotation = R_bc @ M`` with ``M`` mapping layoutkit
station axes to Bitcraze's (``x_bc = z, y_bc = x, z_bc = y``). ``calibs`` are the firmware's
calibration records (:class:`layoutkit.lighthouse.StationCalibration`, Crazyflie convention).

The LH2 base-station id is its channel; each channel's rotor period is the firmware's
``CYCLE_PERIODS`` (:data:`LH2_CYCLE_PERIODS`, 24 MHz deck-clock ticks), so a station read here
carries its channel's exact rotor speed.

Read once per run (:func:`read_system_config` → :class:`SystemConfig`) and passed on as an
object; :func:`write_system_config` is the inverse (atomic).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .._validate import read_structured

__all__ = ["DECK_CLOCK_HZ", "LH2_CYCLE_PERIODS", "SystemConfig", "read_system_config", "system_config_dict",
           "write_system_config", "lh2_channel_rpm"]

#: The Lighthouse deck's timestamp clock (Hz): every station in a system config is timed by it.
DECK_CLOCK_HZ = 24e6
#: LH2 cycle periods per channel, firmware ``CYCLE_PERIODS`` (48 MHz values / 2 → 24 MHz ticks).
LH2_CYCLE_PERIODS = tuple(p // 2 for p in (959000, 957000, 953000, 949000, 947000, 943000, 941000, 939000,
                                           937000, 929000, 919000, 911000, 907000, 901000, 893000, 887000))

# layoutkit station frame → Bitcraze station frame: x_bc = z, y_bc = x, z_bc = y
_LK_TO_BC = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


@dataclass(frozen=True)
class SystemConfig:
    """A Crazyflie lighthouse system configuration: stations (layoutkit frames) and calibrations.

    stations : dict id → :class:`layoutkit.lighthouse.Station` (station pose in the Crazyflie
    world frame, station frame in layoutkit's convention z = boresight); calibs : dict id →
    :class:`~layoutkit.lighthouse.StationCalibration`; system_type : 1 (LH1) or 2 (LH2);
    source : the file it was read from (None for one built in memory).
    """

    stations: dict = field(default_factory=dict)
    calibs: dict = field(default_factory=dict)
    system_type: int = 2
    source: str | None = None

    @property
    def kind(self) -> str:
        """"lh1" or "lh2"."""
        return "lh1" if self.system_type == 1 else "lh2"

    def station_list(self) -> list | None:
        """The stations as a list indexed by base-station id (ids must be 0..k-1), or None when the
        file has no geometry. ValueError naming the file otherwise."""
        ids = sorted(self.stations)
        if ids != list(range(len(ids))):
            raise ValueError(f"{self.source or 'system config'}: base-station ids {ids} are not 0..k-1; "
                             "give --stations")
        return [self.stations[i] for i in ids] or None


def lh2_channel_rpm(channel: int) -> float:
    """Rotor speed (rpm) of LH2 channel ``channel`` (its cycle period; 3000 outside 0-15)."""
    return 60.0 * DECK_CLOCK_HZ / LH2_CYCLE_PERIODS[channel] if 0 <= channel < len(LH2_CYCLE_PERIODS) else 3000.0


def read_system_config(source) -> SystemConfig:
    """Read a Crazyflie system-configuration YAML (module docstring).

    source : path, an already-parsed dict, or a :class:`SystemConfig` (returned as is: callers may
    pass what they were given). Raises ValueError naming the file and what is wrong.
    """
    from ..geometry import nearest_rotation
    from ..lighthouse import Station, StationCalibration, SweepCalibration

    if isinstance(source, SystemConfig):
        return source
    if isinstance(source, dict):
        data, name, src = source, "system config", None
    else:
        import yaml

        path = Path(source)
        name = src = str(path)
        data = read_structured(path, "system configuration", "YAML", yaml.safe_load, yaml.YAMLError)
    if not isinstance(data, dict) or data.get("type") != "lighthouse_system_configuration":
        raise ValueError(f"{name}: expected 'type: lighthouse_system_configuration'")
    if str(data.get("version")) != "1":
        raise ValueError(f"{name}: unsupported version {data.get('version')!r} (expected '1')")
    system_type = int(data.get("systemType", 2))
    kind = "lh1" if system_type == 1 else "lh2"
    stations, calibs = {}, {}
    try:
        for sid, geo in (data.get("geos") or {}).items():
            R = nearest_rotation(np.asarray(geo["rotation"], float))
            stations[int(sid)] = Station(id=str(sid), rotation=R @ _LK_TO_BC,
                                         translation=np.asarray(geo["origin"], float), kind=kind,
                                         rotor_rpm=3600.0 if kind == "lh1" else lh2_channel_rpm(int(sid)),
                                         clock_hz=DECK_CLOCK_HZ)
        for sid, cal in (data.get("calibs") or {}).items():
            sw = tuple(SweepCalibration(**{k: float(s.get(k, 0.0)) for k in SweepCalibration.__dataclass_fields__})
                       for s in cal["sweeps"][:2])
            if len(sw) != 2:
                raise ValueError("two sweeps required")
            calibs[int(sid)] = StationCalibration(sw, int(cal.get("uid", 0)))
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{name}: bad geos/calibs entry ({exc})") from None
    return SystemConfig(stations, calibs, system_type, src)


def system_config_dict(stations: dict, calibs: dict | None = None, system_type: int = 2) -> dict:
    """A system configuration as a dict for ``yaml.safe_dump``: the inverse of
    :func:`read_system_config`. stations : id → :class:`~layoutkit.lighthouse.Station` (world
    pose, layoutkit station frame); calibs : id → :class:`~layoutkit.lighthouse.StationCalibration`
    (firmware convention)."""
    from ..lighthouse import SweepCalibration

    geos = {int(k): {"origin": [float(v) for v in st.translation],
                     "rotation": [[float(v) for v in row] for row in st.rotation @ _LK_TO_BC.T]}
            for k, st in stations.items()}
    cal = {int(k): {"uid": int(c.uid), "sweeps": [{f: float(getattr(sw, f)) for f in SweepCalibration.__dataclass_fields__}
                                                 for sw in c.sweeps]}
           for k, c in (calibs or {}).items()}
    return {"type": "lighthouse_system_configuration", "version": "1", "systemType": int(system_type),
            "geos": geos, "calibs": cal}


def write_system_config(path, config: SystemConfig) -> None:
    """Write ``config`` as a system-configuration YAML at ``path`` (atomically)."""
    import yaml

    from .atomic import atomic_write_text

    atomic_write_text(path, yaml.safe_dump(system_config_dict(config.stations, config.calibs, config.system_type),
                                           sort_keys=False))
