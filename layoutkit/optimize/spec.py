"""What to optimise: the frozen, validated :class:`OptimizeSpec` (and :class:`DenseSpec` for dense envelopes).

One object carries every setting of an optimisation — sensor count, objective, correlation, coverage,
spacing, acceptance half-angle, tilt, method, budget, seed, branch-and-bound and the dense loop — so the
CLI (``layoutkit optimize``), sweeps (``layoutkit sweep``: their option names, converters and defaults
are derived from :data:`SPEC_OPTIONS`), studies and the layout JSON (``"spec"``) all speak the same
language. SI inside (metres, seconds); the field name says the unit where it is not SI
(``half_angle_deg``, ``max_tilt_deg``).

Validation happens once, in :func:`check_field` (called by ``__post_init__``): every number finite and
in range, NaN refused with the field named, choices from their registries (``METHODS``, coverage rules,
objectives). ``from_dict`` (a TOML table or a layout's ``"spec"``) rejects unknown keys.
"""
from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass
from typing import Any, Callable

from ..units import RHO_PAPER

__all__ = ["OptimizeSpec", "DenseSpec", "BNB_CHOICES", "SPEC_OPTIONS", "check_field", "TILT_TOWARD_STATION"]

#: values of ``branch_and_bound``
BNB_CHOICES = ("auto", "off")
#: ``tilt_toward`` value meaning "the mean body-frame direction to the stations over the envelope"
TILT_TOWARD_STATION = "station"


def _number(lo=None, hi=None, lo_open=False, hi_open=False, none=False, integer=False):
    """Converter of a finite number (an integer with ``integer``) in a range; None allowed if ``none``."""
    def conv(v):
        if v is None and none:
            return None
        kind = "an integer" if integer else "a number"
        if isinstance(v, bool) or not isinstance(v, numbers.Integral if integer else numbers.Real):
            raise ValueError(f"expected {kind}, got {v!r}")
        if not math.isfinite(v):
            raise ValueError(f"expected a finite number, got {v!r}")
        v = int(v) if integer else float(v)
        if (lo is not None and (v < lo or (lo_open and v == lo))) or (hi is not None and (v > hi or (hi_open and v == hi))):
            if hi is None:
                rng = f"> {lo}" if lo_open else f">= {lo}"
            else:
                rng = f"in {'(' if lo_open else '['}{lo}, {hi}{')' if hi_open else ']'}"
            raise ValueError(f"expected {kind} {rng}, got {v}")
        return v
    return conv


def _choice(choices: Callable[[], tuple] | tuple, none=False):
    def conv(v):
        if v is None and none:
            return None
        opts = choices() if callable(choices) else choices
        if not isinstance(v, str) or v not in opts:
            raise ValueError(f"expected one of {list(opts)}, got {v!r}")
        return v
    return conv


def _methods():
    from .methods import METHODS

    return tuple(sorted(METHODS))


def _rule(v):
    from ..coverage_rule import check_rule

    try:
        return check_rule(v)
    except ValueError as exc:
        raise ValueError(str(exc).removeprefix("coverage: ")) from None


def _objective(v):
    from .objectives import parse_objective

    if not isinstance(v, str):
        raise ValueError(f"expected a string such as 'worst-adop', got {v!r}")
    try:
        parse_objective(v, (1.0, 1.0) if v.strip().lower().endswith("weighted") else None)
    except ValueError as exc:
        raise ValueError(str(exc).removeprefix("objective: ")) from None
    return v


def _weights(v):
    if v is None:
        return None
    if isinstance(v, str) or not hasattr(v, "__len__") or len(v) != 2:
        raise ValueError(f"expected [a, b] (weights of ADOP^2 and PDOP^2), got {v!r}")
    return tuple(_number(0.0)(x) for x in v)


def _toward(v):
    if v is None or v == TILT_TOWARD_STATION:
        return v
    if isinstance(v, str) or not hasattr(v, "__len__") or len(v) != 3:
        raise ValueError(f"expected '{TILT_TOWARD_STATION}' or a body axis [x, y, z], got {v!r}")
    out = tuple(_number()(x) for x in v)
    if not any(out):
        raise ValueError(f"expected a non-zero body axis, got {list(out)}")
    return out


def _ids(v):
    if isinstance(v, str):
        v = [x.strip() for x in v.split(",") if x.strip()]
    if not isinstance(v, (list, tuple)) or not all(isinstance(x, str) for x in v):
        raise ValueError(f"expected a list of candidate ids (strings), got {v!r}")
    return tuple(v)


def _bool(v):
    if not isinstance(v, bool):
        raise ValueError(f"expected true or false, got {v!r}")
    return v


def _seed_poses(v):
    return v if v == "all" else _number(0, integer=True)(v)


def _later_method(v):
    return _choice(_methods, none=True)(v)


def _dense(v):
    if v is None or isinstance(v, DenseSpec):
        return v
    if isinstance(v, dict):
        return DenseSpec.from_dict(v, where=None)
    raise ValueError(f"expected a DenseSpec, a table of its fields or None, got {v!r}")


@dataclass(frozen=True)
class SpecOption:
    """How one spec field meets the outside: its converter (validation), and its name and scale at the
    CLI / sweep edge (``min_spacing_m`` is ``min_spacing_mm`` there, scale 1e-3); ``sweep``: a sweep
    cell may set it (in ``[base]`` or as an axis)."""

    convert: Callable[[Any], Any]
    edge: str = ""
    scale: float = 1.0
    sweep: bool = True


#: Every field of :class:`OptimizeSpec` and how it is checked (one table, one helper: :func:`check_field`).
SPEC_OPTIONS: dict[str, SpecOption] = {
    "k": SpecOption(_number(1, integer=True)),
    "objective": SpecOption(_objective),
    "weights": SpecOption(_weights),
    "rho": SpecOption(_number(0.0, 1.0, hi_open=True)),
    "min_visible": SpecOption(_number(1, integer=True)),
    "coverage": SpecOption(_rule),
    "coverage_fraction": SpecOption(_number(0.0, 1.0, lo_open=True)),
    "min_spacing_m": SpecOption(_number(0.0), edge="min_spacing_mm", scale=1e-3),
    "half_angle_deg": SpecOption(_number(0.0, 90.0, lo_open=True)),
    "max_tilt_deg": SpecOption(_number(0.0, 90.0, hi_open=True)),
    "tilt_toward": SpecOption(_toward, sweep=False),
    "tilt_directions": SpecOption(_number(1, integer=True), sweep=False),
    "method": SpecOption(_choice(_methods)),
    "time_limit_s": SpecOption(_number(0.0, lo_open=True, none=True)),
    "seed": SpecOption(_number(integer=True, none=True)),
    "branch_and_bound": SpecOption(_choice(BNB_CHOICES), sweep=False),
    "fixed": SpecOption(_ids),
    "dense": SpecOption(_dense, sweep=False),
}

#: Every field of :class:`DenseSpec` and its converter.
DENSE_OPTIONS: dict[str, Callable[[Any], Any]] = {
    "poses": _number(1, integer=True),
    "heldout_poses": _number(1, integer=True),
    "rounds": _number(1, integer=True),
    "coverage_poses": _number(0, integer=True, none=True),
    "add": _number(1, integer=True),
    "seed_poses": _seed_poses,
    "min_sep": _number(0.0),
    "tol": _number(0.0),
    "patience": _number(1, integer=True),
    "max_working": _number(1, integer=True, none=True),
    "first_share": _number(0.0, 1.0, lo_open=True, none=True),
    "later_method": _later_method,
    "later_patience": _number(0, integer=True),
    "later_two_swap": _bool,
    "join_above": _number(0.0, lo_open=True, none=True),
    "coverage_dop": _bool,
    "far_range": _bool,
    "range_sweep": _bool,
    "spare_lit": _number(0, integer=True),
}


def check_field(name: str, value, table=None):
    """The checked (normalised) ``value`` of spec field ``name``; ``ValueError("<name>: ...")`` if bad."""
    table = SPEC_OPTIONS if table is None else table
    conv = table[name]
    conv = conv.convert if isinstance(conv, SpecOption) else conv
    try:
        return conv(value)
    except ValueError as exc:
        raise ValueError(f"{name}: {exc}") from None


def _validate(obj, table):
    for f in dataclasses.fields(obj):
        object.__setattr__(obj, f.name, check_field(f.name, getattr(obj, f.name), table))


def _from_dict(cls, d, where):
    if where is None:
        try:
            return _from_dict(cls, d, "")
        except ValueError as exc:
            raise ValueError(str(exc).removeprefix(": ")) from None
    if not isinstance(d, dict):
        raise ValueError(f"{where}: expected a table of fields, got {d!r}")
    known = [f.name for f in dataclasses.fields(cls)]
    unknown = sorted(set(d) - set(known))
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {unknown}; known: {', '.join(known)}")
    try:
        return cls(**d)
    except TypeError as exc:  # a required field missing
        raise ValueError(f"{where}: {exc}") from None
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None


def _to_dict(obj) -> dict:
    out = {}
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if isinstance(v, DenseSpec):
            v = v.to_dict()
        elif isinstance(v, tuple):
            v = list(v)
        out[f.name] = v
    return out


@dataclass(frozen=True)
class DenseSpec:
    """The adaptive dense-envelope loop (:mod:`layoutkit.optimize.dense`; the module docstring explains
    every field). poses : dense poses drawn from the envelope (seed ``envelope.seed + 1``);
    heldout_poses : fresh poses (seed + 2) the report scores the layout on; coverage_poses : poses
    (seed + 3) checked for coverage every round (None: 4 × ``poses``); rounds, add, seed_poses, min_sep,
    tol, patience, max_working, first_share, later_method, later_patience, later_two_swap, join_above,
    coverage_dop, far_range, range_sweep : the loop's knobs. spare_lit : lit sensors the loop requires at its
    poses beyond ``min_visible`` (a margin: a fresh pose between sampled ones then has to lose
    ``spare_lit + 1`` sensors to drop below ``min_visible``); the held-out estimate and the reports still
    count coverage with ``min_visible``."""

    poses: int
    heldout_poses: int = 2000
    rounds: int = 40
    coverage_poses: "int | None" = None
    add: int = 192
    seed_poses: "int | str" = "all"
    min_sep: float = 0.05
    tol: float = 0.02
    patience: int = 8
    max_working: "int | None" = None
    first_share: "float | None" = None
    later_method: "str | None" = "polish"
    later_patience: int = 2
    later_two_swap: bool = False
    join_above: "float | None" = None
    coverage_dop: bool = False
    far_range: bool = False
    range_sweep: bool = False
    spare_lit: int = 0

    def __post_init__(self):
        _validate(self, DENSE_OPTIONS)

    @property
    def coverage_count(self) -> int:
        """Coverage-only poses per round (``coverage_poses``, default 4 × ``poses``)."""
        return 4 * self.poses if self.coverage_poses is None else self.coverage_poses

    @classmethod
    def from_dict(cls, d: dict, where: str = "dense") -> "DenseSpec":
        return _from_dict(cls, d, where)

    def to_dict(self) -> dict:
        return _to_dict(self)


@dataclass(frozen=True)
class OptimizeSpec:
    """Settings of one optimisation (validated at construction; frozen).

    k : sensors to place. objective : ``<worst|mean|pNN>-<adop|pdop|weighted>``
    (:func:`layoutkit.optimize.parse_objective`); weights : ``(a, b)`` of ADOP² (deg²) and PDOP² (m²) for
    ``*-weighted``. rho : same-rotor angle correlation (Chen eq. 19; paper 0.8717). min_visible : m, lit
    sensors needed at a pose; coverage : the rule of "lit" with several stations
    (:mod:`layoutkit.coverage_rule`); coverage_fraction : share of the poses that must be covered.
    min_spacing_m : minimum distance between chosen sensors (m). half_angle_deg : photodiode acceptance
    half-angle (deg; a property of the candidates' visibility, see
    :class:`layoutkit.optimize.design.DesignProblem`). max_tilt_deg, tilt_toward, tilt_directions : sensor
    tilt as a design variable (:mod:`layoutkit.optimize.tilt`; ``tilt_toward`` None, ``"station"`` or a body
    axis (3,)). method : a name of :data:`layoutkit.optimize.METHODS`. time_limit_s : wall budget (s; None:
    the method's default, 100 s for the pipeline). seed : of the search's random generator (and of
    candidate sampling; None: fresh entropy). branch_and_bound : "auto" or "off". fixed : candidate ids
    placed in advance. dense : the dense-envelope loop (:class:`DenseSpec`) or None (design poses only).
    """

    k: int
    objective: str = "worst-adop"
    weights: "tuple | None" = None
    rho: float = RHO_PAPER
    min_visible: int = 4
    coverage: str = "any-station"
    coverage_fraction: float = 1.0
    min_spacing_m: float = 0.0
    half_angle_deg: float = 60.0
    max_tilt_deg: float = 0.0
    tilt_toward: "str | tuple | None" = None
    tilt_directions: int = 4
    method: str = "pipeline"
    time_limit_s: "float | None" = None
    seed: "int | None" = 0
    branch_and_bound: str = "auto"
    fixed: tuple = ()
    dense: "DenseSpec | None" = None

    def __post_init__(self):
        _validate(self, SPEC_OPTIONS)
        if self.objective.strip().lower().endswith("weighted") and self.weights is None:
            raise ValueError(f"weights: objective {self.objective!r} needs weights (a, b) of ADOP² (deg²) and "
                             "PDOP² (m²); no silent default")
        if len(self.fixed) > self.k:
            raise ValueError(f"fixed: {len(self.fixed)} fixed sensors exceed k = {self.k}")

    @property
    def tilted(self) -> bool:
        return self.max_tilt_deg > 0

    def replace(self, **changes) -> "OptimizeSpec":
        """A copy with ``changes`` (validated again)."""
        return dataclasses.replace(self, **changes)

    @classmethod
    def from_dict(cls, d: dict, where: str = "spec") -> "OptimizeSpec":
        """From a table (TOML, a layout's ``"spec"``); unknown keys are an error naming them."""
        return _from_dict(cls, d, where)

    def to_dict(self) -> dict:
        """JSON-able dict of every field (``dense`` as a dict or None); round-trips through :meth:`from_dict`."""
        return _to_dict(self)
