"""Design-sweep files: a base optimisation problem and axes to sweep, validated into frozen cells.

A sweep file is TOML (docs/distributed.md)::

    [base]
    mesh = "target.stl"          # paths: relative to this file, or absolute
    envelope = "envelope.toml"
    spacing_mm = 8.0             # or: candidates = "cands.json"
    objective = "worst-adop"
    rho = 0.8717
    time_limit_s = 60
    [axes]
    k = [12, 16]
    half_angle_deg = [55.0, 65.0]

Every ``layoutkit optimize`` option may appear in ``[base]`` under its flag name without dashes
(:func:`options`; the optimisation settings are those of :class:`layoutkit.optimize.OptimizeSpec`); those marked sweepable also in ``[axes]`` as a list. The cells are the Cartesian
product of the axes, in file order (the first axis varies slowest). A key in both tables is an
error, and so is any unknown key: the message names the file and the key.

Each :class:`Cell` has a stable id built from its axis values (``k12_half_angle_deg55-1f0a9c3e``):
the same cell in an edited sweep keeps its id, so results on disk can be reused, and its
``input_hash`` (SHA-256 of every option plus the bytes of every input file) tells whether they
still apply.
"""
from __future__ import annotations

import functools
import hashlib
import itertools
import json
import math
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from .._validate import read_structured
from ..units import LENGTH_UNIT_NAMES

__all__ = ["options", "defaults", "SweepConfig", "Cell", "load_sweep", "parse_sweep", "cell_spec"]

_TOP = {"name", "description", "base", "axes"}


def _int(lo=None):
    def conv(v):
        if isinstance(v, bool) or not isinstance(v, int):
            raise ValueError(f"expected an integer{'' if lo is None else f' >= {lo}'}, got {v!r}")
        if lo is not None and v < lo:
            raise ValueError(f"expected an integer >= {lo}, got {v}")
        return int(v)
    return conv


def _float(lo=None, lo_open=False):
    def conv(v):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ValueError(f"expected a number, got {v!r}")
        v = float(v)
        if lo is not None and (v < lo or (lo_open and v == lo)):
            raise ValueError(f"expected a number {'>' if lo_open else '>='} {lo}, got {v}")
        return v
    return conv


def _str(choices=None):
    def conv(v):
        if not isinstance(v, str):
            raise ValueError(f"expected a string, got {v!r}")
        if choices is not None and v not in choices:
            raise ValueError(f"expected one of {', '.join(choices)}, got {v!r}")
        return v
    return conv


def _path(v):
    if not isinstance(v, str) or not v:
        raise ValueError(f"expected a file path (string), got {v!r}")
    return v


def _bool(v):
    if not isinstance(v, bool):
        raise ValueError(f"expected true or false, got {v!r}")
    return v


def _str_list(v):
    if isinstance(v, str):
        v = [x.strip() for x in v.split(",") if x.strip()]
    if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
        raise ValueError(f"expected a list of strings, got {v!r}")
    return tuple(v)


@dataclass(frozen=True)
class _Opt:
    convert: Callable[[Any], Any]
    sweepable: bool = True
    is_path: bool = False
    #: the :class:`layoutkit.optimize.OptimizeSpec` field and the scale from this option's unit to it
    spec_field: "str | None" = None
    scale: float = 1.0


def _spec_converter(name, scale):
    """Converter of a sweep value of spec field ``name`` (unit ``1/scale`` of it): the spec's own check."""
    from ..optimize.spec import check_field

    def conv(v):
        if isinstance(v, list):
            v = tuple(v)
        if scale != 1.0 and (isinstance(v, bool) or not isinstance(v, (int, float))):
            raise ValueError(f"expected a number, got {v!r}")
        try:
            out = check_field(name, v * scale if scale != 1.0 else v)
        except ValueError as exc:
            raise ValueError(str(exc).removeprefix(f"{name}: ")) from None
        return float(v) if scale != 1.0 else out
    return conv


def _spec_options() -> dict:
    """The sweep options that are :class:`OptimizeSpec` fields: the spec's names (the CLI's unit where the
    edge name says another, e.g. ``min_spacing_mm``), its converters and its defaults."""
    from ..optimize.spec import SPEC_OPTIONS

    out = {}
    for name, so in SPEC_OPTIONS.items():
        if not so.sweep:
            continue
        edge = so.edge or name
        out[edge] = _Opt(_spec_converter(name, so.scale), sweepable=name not in ("fixed",), spec_field=name,
                         scale=so.scale)
    return out


def _spec_defaults() -> dict:
    """Defaults of the spec fields a sweep may set, in the sweep's units (None defaults are left out)."""
    import dataclasses

    from ..optimize.spec import SPEC_OPTIONS, OptimizeSpec

    out = {}
    for f in dataclasses.fields(OptimizeSpec):
        so = SPEC_OPTIONS[f.name]
        if not so.sweep or f.default is dataclasses.MISSING or f.default is None:
            continue
        out[so.edge or f.name] = f.default / so.scale if so.scale != 1.0 else f.default
    return out


#: The options that say how the problem is loaded (:meth:`layoutkit.optimize.DesignProblem.load`).
_LOAD_OPTIONS: dict[str, _Opt] = {
    "mesh": _Opt(_path, True, True),
    "envelope": _Opt(_path, True, True),
    "candidates": _Opt(_path, True, True),
    "spacing_mm": _Opt(_float(0.0, lo_open=True)),
    "max_candidates": _Opt(_int(1)),
    "keepout_box": _Opt(_str_list, False),
    "units": _Opt(_str(LENGTH_UNIT_NAMES), False),
    "allow_odd_size": _Opt(_bool, False),
}


@functools.cache
def options() -> dict:
    """Every option of a sweep cell: ``name -> _Opt(converter, may be an axis, is a path, spec field)``;
    the optimisation settings are the fields of :data:`layoutkit.optimize.spec.SPEC_OPTIONS` (built on
    first use: importing this module stays cheap)."""
    return {**_LOAD_OPTIONS, **_spec_options()}


@functools.cache
def defaults() -> dict:
    """Defaults of the options a sweep leaves out: the spec's own (:class:`layoutkit.optimize.OptimizeSpec`)
    and the neutral loading choices (metres, no keep-out, odd sizes refused)."""
    return {**_spec_defaults(), "units": "m", "keepout_box": (), "allow_odd_size": False}

#: Options that change the prepared problem (mesh, candidates, visibility); the others only the search.
PREP_KEYS = ("mesh", "units", "allow_odd_size", "envelope", "candidates", "spacing_mm", "max_candidates",
             "keepout_box", "half_angle_deg", "max_tilt_deg", "seed")


def cell_spec(opts: dict):
    """The :class:`layoutkit.optimize.OptimizeSpec` of a cell's options (branch-and-bound off: a cell must
    be reproducible across schedulers and resumes, and B&B's bound depends on timing)."""
    from ..optimize import OptimizeSpec

    kw = {o.spec_field: opts[name] * o.scale if o.scale != 1.0 else opts[name]
          for name, o in options().items() if o.spec_field is not None and opts.get(name) is not None}
    return OptimizeSpec(**kw, branch_and_bound="off")


@dataclass(frozen=True)
class Cell:
    """One optimisation of a sweep.

    index : position in the sweep; cell_id : stable name (file stem under ``DIR/cells/``);
    axes : ``((axis, value as written), ...)`` in ``[axes]`` order; options : ``((name, value), ...)``
    sorted, every option of the cell with paths resolved to absolute; input_hash : SHA-256 hex of
    the options and the contents of the input files.
    """

    index: int
    cell_id: str
    axes: tuple
    options: tuple
    input_hash: str

    @property
    def opts(self) -> dict:
        return dict(self.options)

    def prep_key(self) -> tuple:
        o = self.opts
        return tuple((k, o.get(k)) for k in PREP_KEYS)


@dataclass(frozen=True)
class SweepConfig:
    """A validated sweep file: path, name, base options, axes ``((name, (values...)), ...)``, cells."""

    path: str
    name: str
    base: tuple
    axes: tuple
    cells: tuple

    @property
    def axis_names(self) -> tuple:
        return tuple(a for a, _ in self.axes)


def load_sweep(path) -> SweepConfig:
    """Read and validate a sweep TOML (``ValueError`` "<file>: <key>: ..." on any problem)."""
    path = Path(path)
    d = read_structured(path, "sweep", "TOML", tomllib.loads, tomllib.TOMLDecodeError)
    return parse_sweep(d, path)


def parse_sweep(d: dict, path) -> SweepConfig:
    """Validate the dict of a sweep file read from ``path`` (paths resolve against its folder)."""
    path = Path(path)
    where = str(path)
    OPTIONS, DEFAULTS = options(), defaults()

    def err(key, msg):
        return ValueError(f"{where}: {key}: {msg}")

    for k in d:
        if k not in _TOP:
            raise err(k, f"unknown key (expected {', '.join(sorted(_TOP))})")
    base_in, axes_in = d.get("base", {}), d.get("axes", {})
    for nm, tab in (("base", base_in), ("axes", axes_in)):
        if not isinstance(tab, dict):
            raise err(nm, "expected a table [" + nm + "]")
    base = {}
    for k, v in base_in.items():
        if k not in OPTIONS:
            raise err(f"base.{k}", f"unknown option (known: {', '.join(OPTIONS)})")
        try:
            base[k] = OPTIONS[k].convert(v)
        except ValueError as exc:
            raise err(f"base.{k}", str(exc)) from None
    axes = []
    for k, vals in axes_in.items():
        if k not in OPTIONS:
            raise err(f"axes.{k}", f"unknown option (known: {', '.join(OPTIONS)})")
        if not OPTIONS[k].sweepable:
            raise err(f"axes.{k}", "cannot be swept; put it in [base]")
        if k in base:
            raise err(f"axes.{k}", "also given in [base]; keep one")
        if not isinstance(vals, list) or not vals:
            raise err(f"axes.{k}", f"expected a non-empty list of values, got {vals!r}")
        conv = []
        for i, v in enumerate(vals):
            try:
                conv.append(OPTIONS[k].convert(v))
            except ValueError as exc:
                raise err(f"axes.{k}[{i}]", str(exc)) from None
        if len(set(map(repr, conv))) != len(conv):
            raise err(f"axes.{k}", f"repeated values in {vals!r}")
        axes.append((k, tuple(conv)))
    for req in ("mesh", "envelope", "k"):
        if req not in base and all(a != req for a, _ in axes):
            raise err(req, "required (in [base] or [axes])")
    has = lambda key: key in base or any(a == key for a, _ in axes)  # noqa: E731
    if has("candidates") and has("spacing_mm"):
        raise err("candidates", "give either candidates (a file) or spacing_mm (sampling), not both")
    folder = path.resolve().parent
    file_hash = {}

    def resolve(v):
        p = Path(v)
        p = p if p.is_absolute() else folder / p
        if not p.is_file():
            raise err(v, f"no such file ({p})")
        return str(p)

    def fhash(p):
        if p not in file_hash:
            file_hash[p] = hashlib.sha256(Path(p).read_bytes()).hexdigest()
        return file_hash[p]

    cells = []
    names = [a for a, _ in axes]
    for i, combo in enumerate(itertools.product(*[v for _, v in axes]) if axes else [()]):
        o = {**DEFAULTS, **base, **dict(zip(names, combo))}
        for k in list(o):
            if OPTIONS[k].is_path:
                o[k] = resolve(o[k])
        if o["objective"].endswith("weighted") and "weights" not in o:
            raise err("weights", f"objective {o['objective']!r} needs weights = [a, b]")

        hashed = {k: ({"sha256": fhash(v)} if OPTIONS[k].is_path else v) for k, v in o.items()}
        h = hashlib.sha256(json.dumps(hashed, sort_keys=True, default=list).encode()).hexdigest()
        ax = tuple(zip(names, combo))
        cells.append(Cell(i, _cell_id(ax), ax, tuple(sorted(o.items())), h))
    ids = [c.cell_id for c in cells]
    if len(set(ids)) != len(ids):  # distinct values with the same slug and hash prefix: practically never
        raise err("axes", "two cells got the same id; rename the files")
    return SweepConfig(str(path), str(d.get("name", path.stem)), tuple(sorted(base.items())), tuple(axes),
                       tuple(cells))


def _cell_id(axes: tuple) -> str:
    """``k12_half_angle_deg55-<8 hex>``: readable axis values (file stems for paths) + a hash of them."""
    OPTIONS = options()
    if not axes:
        return "base"
    parts = []
    for k, v in axes:
        s = Path(v).stem if OPTIONS[k].is_path else (f"{v:g}" if isinstance(v, float) else str(v))
        parts.append(f"{k}{s}")
    slug = re.sub(r"[^A-Za-z0-9.+-]+", "_", "_".join(parts))[:80]
    h = hashlib.sha256(json.dumps([[k, v] for k, v in axes], default=list).encode()).hexdigest()[:8]
    return f"{slug}-{h}"
