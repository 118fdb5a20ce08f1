"""Operating envelopes: where the target may be and how it may be turned, as a seeded pose set.

An envelope file is TOML (docs/envelope.md)::

    name = "chen2024"
    count = 200                    # number of poses
    seed = 1
    range_m = [1.0, 3.0]           # distance of the body origin from the reference station
    boresight_cone_deg = 30.0      # half-angle of the cone around that station's boresight

    [attitude]
    kind = "cone"                  # "uniform" | "cone" | "trajectory"
    nominal_rotvec_deg = [180, 0, 0]
    half_angle_deg = 45.0

    [[station]]
    id = "A"
    position_m = [0, 0, 0]
    rotvec_deg = [0, 0, 0]         # or look_at_m = [x, y, z]
    kind = "lh1"
    fov_deg = 120

Positions: the body origin is drawn uniformly in range (distance) and uniformly over the
spherical cap of ``boresight_cone_deg`` around the boresight (+z) of the reference station
(``reference_station``, default the first). Attitudes (body in the WORLD frame): ``uniform``
(Haar on SO(3)), ``cone`` (Haar measure restricted to the rotations within ``half_angle_deg``
of ``R_nominal``, i.e. ``R = exp([w]x) R_nominal`` with ``|w| <= half_angle``), or ``trajectory``
(a pose table, :mod:`layoutkit.io.poses`: ``t,rx,ry,rz,tx,ty,tz`` at least, rotation vector in
RADIANS — or columns ``rx_deg,ry_deg,rz_deg`` — and metres, body in the world frame; it gives the whole pose and ``range_m``/``boresight_cone_deg`` are not
used). Without ``[[station]]`` one LH1 station sits at the world origin, so the world frame is
the station frame (said in a :class:`~layoutkit._validate.ValidationWarning`).

Pose convention everywhere: ``p_world = R p_body + t``.
"""
from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .geometry import look_at_rotation, random_rotations, rotvec_to_matrix
from ._validate import check_range, read_structured
from .lighthouse import Station

__all__ = ["ATTITUDE_KINDS", "Envelope", "load_envelope", "envelope_set", "sample_cone_rotations",
           "sample_cone_directions"]

ATTITUDE_KINDS = ("uniform", "cone", "trajectory")

_TOP_KEYS = {"name", "description", "count", "seed", "range_m", "boresight_cone_deg",
             "reference_station", "attitude", "station"}
_ATT_KEYS = {"uniform": {"kind"}, "cone": {"kind", "nominal_rotvec_deg", "half_angle_deg"},
             "trajectory": {"kind", "file"}}
_ST_KEYS = {"id", "position_m", "rotvec_deg", "look_at_m", "kind", "fov_deg", "rotor_rpm", "clock_hz"}


def sample_cone_directions(count: int, half_angle: float, rng: np.random.Generator) -> np.ndarray:
    """``count`` unit vectors ``(count, 3)`` uniform on the cap of ``half_angle`` (rad) around +z."""
    cos_min = math.cos(half_angle)
    z = rng.uniform(cos_min, 1.0, count)  # uniform in z = uniform area on the cap (Archimedes)
    phi = rng.uniform(0.0, 2 * np.pi, count)
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def sample_cone_rotations(count: int, nominal, half_angle: float, rng: np.random.Generator) -> np.ndarray:
    """``count`` rotations ``(count, 3, 3)`` Haar-uniform within geodesic angle ``half_angle`` (rad) of ``nominal``.

    ``R = exp([w]x) nominal``; axis of ``w`` uniform on the sphere, angle ``a`` with the Haar
    density ``∝ 1 - cos a`` on ``[0, half_angle]`` (inverse CDF ``a - sin a`` by interpolation).
    """
    half = float(min(half_angle, np.pi))
    grid = np.linspace(0.0, half, 2049)
    cdf = grid - np.sin(grid)
    a = np.interp(rng.uniform(0.0, cdf[-1], count), cdf, grid)
    axis = rng.normal(size=(count, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    return rotvec_to_matrix(axis * a[:, None]) @ np.asarray(nominal, float)


@dataclass(frozen=True)
class Envelope:
    """A seeded operating envelope (see the module docstring for the meaning of each field).

    range_m : (min, max) m; boresight_cone_deg : deg; attitude : one of :data:`ATTITUDE_KINDS`;
    nominal_rotvec_deg : (3,) deg; attitude_half_angle_deg : deg; trajectory : CSV path or None;
    count : number of poses (for a trajectory: evenly subsample to at most ``count``, 0 = all rows);
    seed : int; stations : tuple of :class:`Station`; reference_station : index into ``stations``.
    """

    range_m: tuple = (1.0, 3.0)
    boresight_cone_deg: float = 30.0
    attitude: str = "uniform"
    nominal_rotvec_deg: tuple = (0.0, 0.0, 0.0)
    attitude_half_angle_deg: float = 180.0
    trajectory: str | None = None
    count: int = 100
    seed: int = 0
    stations: tuple = field(default_factory=lambda: (Station(),))
    reference_station: int = 0
    name: str = ""
    description: str = ""

    def __post_init__(self):
        r = tuple(float(x) for x in self.range_m)
        if len(r) != 2 or not (0.0 < r[0] <= r[1]) or not all(map(math.isfinite, r)):
            raise ValueError(f"range_m: expected [min, max] with 0 < min <= max, got {list(self.range_m)}")
        check_range(r[1], f"range_m {list(r)}")
        if not (0.0 <= float(self.boresight_cone_deg) <= 90.0):
            raise ValueError(f"boresight_cone_deg: expected a half-angle in [0, 90], got {self.boresight_cone_deg}")
        if self.attitude not in ATTITUDE_KINDS:
            raise ValueError(f"attitude.kind: expected one of {list(ATTITUDE_KINDS)}, got {self.attitude!r}")
        nom = tuple(float(x) for x in self.nominal_rotvec_deg)
        if len(nom) != 3 or not all(map(math.isfinite, nom)):
            raise ValueError(f"attitude.nominal_rotvec_deg: expected 3 finite numbers, got {list(self.nominal_rotvec_deg)}")
        if not (0.0 <= float(self.attitude_half_angle_deg) <= 180.0):
            raise ValueError(f"attitude.half_angle_deg: expected [0, 180], got {self.attitude_half_angle_deg}")
        if self.attitude == "trajectory" and not self.trajectory:
            raise ValueError("attitude.file: a 'trajectory' attitude needs a CSV file")
        if (isinstance(self.count, bool) or not isinstance(self.count, (int, np.integer)) or self.count < 0
                or (self.count == 0 and self.attitude != "trajectory")):
            raise ValueError(f"count: expected a positive integer, got {self.count!r}")
        stations = tuple(self.stations)
        if not stations or not all(isinstance(s, Station) for s in stations):
            raise ValueError("station: need at least one [[station]]")
        ids = [s.id for s in stations]
        if len(set(ids)) != len(ids):
            raise ValueError(f"station: ids must be unique, got {ids}")
        if not (0 <= int(self.reference_station) < len(stations)):
            raise ValueError(f"reference_station: expected an index in [0, {len(stations)}), got {self.reference_station}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)):
            raise ValueError(f"seed: expected an integer, got {self.seed!r}")
        object.__setattr__(self, "range_m", r)
        object.__setattr__(self, "nominal_rotvec_deg", nom)
        object.__setattr__(self, "stations", stations)
        object.__setattr__(self, "count", int(self.count))
        object.__setattr__(self, "seed", int(self.seed))

    @classmethod
    def from_dict(cls, d: dict, base_dir=None) -> "Envelope":
        """Build from the TOML structure (keys as in the module docstring); unknown keys are errors.

        base_dir : directory against which a relative trajectory file is resolved.
        """
        if not isinstance(d, dict):
            raise ValueError("envelope: expected a table of keys")
        if not d:
            raise ValueError("envelope: the file sets nothing (empty); give at least range_m, boresight_cone_deg and "
                             "an [attitude] table (docs/envelope.md) rather than run on silent defaults")
        _reject_unknown(d, _TOP_KEYS, "envelope")
        att = d.get("attitude", {"kind": "uniform"})
        if not isinstance(att, dict):
            raise ValueError("attitude: expected a table [attitude] with a 'kind'")
        kind = att.get("kind", "uniform")
        if kind not in ATTITUDE_KINDS:
            raise ValueError(f"attitude.kind: expected one of {list(ATTITUDE_KINDS)}, got {kind!r}")
        _reject_unknown(att, _ATT_KEYS[kind], f"attitude (kind = {kind!r})")
        traj = att.get("file")
        if traj is not None and base_dir is not None and not Path(traj).is_absolute():
            traj = str(Path(base_dir) / traj)
        raw_st = d.get("station", [])
        if not isinstance(raw_st, list):
            raise ValueError("station: expected an array of tables [[station]]")
        stations = tuple(_station_from_dict(s, k) for k, s in enumerate(raw_st))
        if not stations:  # documented default, but never silent: where the lighthouse is sets every pose
            import warnings

            from ._validate import ValidationWarning

            stations = (Station(),)
            warnings.warn(ValidationWarning(
                "station: no [[station]] table: one LH1 station 'A' (field of view 120 deg) at the world origin "
                "looking along +z is assumed, so the world frame is the station frame; add a [[station]] table "
                "(position_m, rotvec_deg or look_at_m, kind) to say where your lighthouse is"), stacklevel=2)
        try:
            return cls(
                range_m=tuple(d.get("range_m", (1.0, 3.0))),
                boresight_cone_deg=float(d.get("boresight_cone_deg", 30.0)),
                attitude=kind,
                nominal_rotvec_deg=tuple(att.get("nominal_rotvec_deg", (0.0, 0.0, 0.0))),
                attitude_half_angle_deg=float(att.get("half_angle_deg", 180.0)),
                trajectory=traj,
                count=d.get("count", 0 if kind == "trajectory" else 100),
                seed=d.get("seed", 0),
                stations=stations,
                reference_station=d.get("reference_station", 0),
                name=str(d.get("name", "")),
                description=str(d.get("description", "")),
            )
        except TypeError as exc:
            raise ValueError(f"envelope: wrong value type ({exc})") from None

    def poses(self):
        """The pose set: ``(rotations (P, 3, 3), translations (P, 3))`` of the body in the WORLD frame.

        Deterministic for a given ``seed``. ``p_world = R p_body + t``.
        """
        if self.attitude == "trajectory":
            return _read_trajectory(self.trajectory, self.count)
        rng = np.random.default_rng(self.seed)
        ref = self.stations[self.reference_station]
        dirs = sample_cone_directions(self.count, np.deg2rad(self.boresight_cone_deg), rng)
        dist = rng.uniform(self.range_m[0], self.range_m[1], self.count)
        t = (dirs * dist[:, None]) @ ref.rotation.T + ref.translation
        if self.attitude == "uniform":
            R = random_rotations(self.count, rng)
        else:
            nominal = rotvec_to_matrix(np.deg2rad(self.nominal_rotvec_deg))
            R = sample_cone_rotations(self.count, nominal, np.deg2rad(self.attitude_half_angle_deg), rng)
        return R, t

    def to_dict(self) -> dict:
        """The TOML structure (stations with rotvec_deg); round-trips through :meth:`from_dict`."""
        att = {"kind": self.attitude}
        if self.attitude == "cone":
            att.update(nominal_rotvec_deg=list(self.nominal_rotvec_deg), half_angle_deg=self.attitude_half_angle_deg)
        if self.attitude == "trajectory":
            att["file"] = self.trajectory
        from .geometry import matrix_to_rotvec

        return {
            "name": self.name, "description": self.description, "count": self.count, "seed": self.seed,
            "range_m": list(self.range_m), "boresight_cone_deg": self.boresight_cone_deg,
            "reference_station": self.reference_station, "attitude": att,
            "station": [{"id": s.id, "position_m": s.translation.tolist(),
                         "rotvec_deg": np.rad2deg(matrix_to_rotvec(s.rotation)).tolist(), "kind": s.kind,
                         "fov_deg": s.fov_deg, "rotor_rpm": s.rotor_rpm, "clock_hz": s.clock_hz}
                        for s in self.stations],
        }


def load_envelope(path) -> Envelope:
    """Read an envelope TOML file; ``ValueError`` naming the file for bad syntax or content."""
    import warnings

    path = Path(path)
    d = read_structured(path, "envelope", "TOML", tomllib.loads, tomllib.TOMLDecodeError)
    try:
        with warnings.catch_warnings(record=True) as caught:  # re-issued below, naming this file
            warnings.simplefilter("always")
            env = Envelope.from_dict(d, base_dir=path.parent)
            if env.attitude == "trajectory":
                env.poses()  # read the CSV now so that its errors name this file
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
    for w in caught:
        warnings.warn(type(w.message)(f"{path}: {w.message}"), stacklevel=2)
    return env


def envelope_set(envelope, count=None, seed=None):
    """``(Envelope, R (P, 3, 3), t (P, 3))`` of ``envelope`` (path or :class:`Envelope`), optionally with
    another pose ``count`` or ``seed`` (a dense or held-out set of the same envelope); world frame."""
    import dataclasses

    env = envelope if isinstance(envelope, Envelope) else load_envelope(envelope)
    ch = {}
    if count is not None:
        ch["count"] = int(count)
    if seed is not None:
        ch["seed"] = int(seed)
    if ch:
        env = dataclasses.replace(env, **ch)
    R, t = env.poses()
    return env, R, t


def _reject_unknown(d: dict, allowed: set, where: str) -> None:
    unknown = sorted(set(d) - allowed)
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {unknown}; allowed: {sorted(allowed)}")


def _vec3(v, where):
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: expected 3 numbers, got {v!r}") from None
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{where}: expected 3 finite numbers, got {v!r}")
    return a


def _station_from_dict(s, k: int) -> Station:
    where = f"station {k}"
    if not isinstance(s, dict):
        raise ValueError(f"{where}: expected a table")
    _reject_unknown(s, _ST_KEYS, where)
    pos = _vec3(s.get("position_m", (0.0, 0.0, 0.0)), f"{where}.position_m")
    if "rotvec_deg" in s and "look_at_m" in s:
        raise ValueError(f"{where}: give either rotvec_deg or look_at_m, not both")
    if "look_at_m" in s:
        direction = _vec3(s["look_at_m"], f"{where}.look_at_m") - pos
        if np.linalg.norm(direction) < 1e-9:
            raise ValueError(f"{where}.look_at_m: must differ from position_m")
        R = look_at_rotation(direction).T  # rows of look_at_rotation = station axes in the world
    else:
        R = rotvec_to_matrix(np.deg2rad(_vec3(s.get("rotvec_deg", (0.0, 0.0, 0.0)), f"{where}.rotvec_deg")))
    kw = {key: float(s[key]) for key in ("fov_deg", "rotor_rpm", "clock_hz") if key in s}
    if "fov_deg" in kw and not 0.0 < kw["fov_deg"] <= 180.0:
        raise ValueError(f"{where}.fov_deg: expected a full field of view in (0, 180] deg, got {kw['fov_deg']:g} "
                         "(0 would leave every sensor unlit)")
    for key in ("rotor_rpm", "clock_hz"):
        if key in kw and not kw[key] > 0:
            raise ValueError(f"{where}.{key}: expected a positive number, got {kw[key]:g}")
    try:
        return Station(id=str(s.get("id", chr(ord("A") + k))), rotation=R, translation=pos,
                       kind=str(s.get("kind", "lh1")), **kw)
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None


def _read_trajectory(path, count: int):
    """A pose table (:mod:`layoutkit.io.poses`: rotation vector rad — or ``rx_deg`` columns — and
    metres) → body poses in the world, evenly subsampled to ``count``."""
    from .io.poses import read_poses

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"attitude.file: no such trajectory file {str(path)!r}")
    tb = read_poses(path, min_rows=1)
    rv, tr = tb.rotvec, tb.translation
    if not (np.all(np.isfinite(rv)) and np.all(np.isfinite(tr))):
        raise ValueError(f"{path}: trajectory has non-finite values")
    if count and count < len(tb):
        k = np.round(np.linspace(0, len(tb) - 1, count)).astype(int)
        rv, tr = rv[k], tr[k]
    return rotvec_to_matrix(rv), tr
