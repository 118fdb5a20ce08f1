"""One click option per quantity (after rasterio's ``rio/options.py``).

Why one module of ~610 lines: every option of every command lives here by design — one spelling,
unit, range and default per quantity is only checkable when they are in one place.

Every command that takes a quantity takes it through the object defined here, so a quantity has
one spelling, one unit, one range and one default across the whole CLI. Old spellings stay for
one release as *hidden* aliases that print a one-line deprecation note to stderr and feed the
same parameter (with a unit conversion where the old spelling had another unit).

Conventions:
- lengths and angles name their unit in the flag (``--distance-m``, ``--half-angle-deg``);
  the Python parameter a command receives is SI unless its name says otherwise
  (``--sigma-arcsec`` arrives as ``sigma`` in radians);
- ``--json`` is always a flag that prints JSON to stdout; a JSON file is ``--json-out FILE``;
- ``--out`` is a file, ``--out-dir`` / ``--report`` are folders;
- choices that name an algorithm come from its registry (:func:`registry_choice`).

Only click and the unit constants are imported here (no numpy): importing the CLI stays cheap.
"""
from __future__ import annotations

import importlib
from typing import Callable, Iterable

import click
from click.core import ParameterSource

from ..units import ARCSEC, LENGTH_UNIT_NAMES, LENGTH_UNITS, RHO_PAPER, SIGMA_THETA_PAPER

__all__ = [
    "option", "explicit", "registry_choice", "sigma_option", "rho_option", "half_angle_option", "units_option",
    "seed_option", "json_flag", "json_out_option", "out_file_option", "out_dir_option",
    "report_option", "layout_option", "envelope_option", "distance_m_option", "length_mm_option", "refine_stations_option", "allow_odd_size_option",
    "overwrite_option", "coverage_option", "COVERAGE_CHOICES", "min_visible_option", "FILTER_CHOICES",
    "filter_options", "protocol_option", "port_option", "time_limit_option", "RegistryChoice", "RHO_RANGE",
    "SIGMA_RANGE", "SIGMA_RANGE_SIMULATION", "camera_options", "camera_model_option", "corner_sigma_option",
    "Number", "finite", "finite_types", "PROBABILITY", "POSITIVE", "NONNEGATIVE", "FINITE",
    "system_config_option", "stations_option", "ignore_calibration_option", "solve_mode_option", "SOLVE_MODES", "scheduler_option", "workers_option",
]

#: names of :data:`layoutkit.coverage_rule.COVERAGE_RULES` (listed here so that importing the CLI
#: stays numpy-free; a test checks they match the registry)
COVERAGE_CHOICES = ("any-station", "each-station", "joint")


class Number(click.FloatRange):
    """A float option's type: a :class:`click.FloatRange` that also refuses NaN and, unless
    ``allow_inf``, +-infinity — click's own ranges let NaN through (every comparison with NaN is
    false). The one numeric boundary of the CLI: :func:`finite_types` gives every float parameter
    of every command this type, so a new command is covered without a line of its own.
    ``what`` names the quantity's unit or meaning in the refusal (``"a probability"``).
    """

    name = "number"

    def __init__(self, min=None, max=None, min_open=False, max_open=False, clamp=False, *,
                 allow_inf: bool = False, what: str | None = None):
        super().__init__(min, max, min_open, max_open, clamp)
        self.allow_inf = allow_inf
        self.what = what

    def convert(self, value, param, ctx):
        import math

        try:
            v = float(value)
        except (TypeError, ValueError):
            self.fail(f"{value!r} is not a number", param, ctx)
        if math.isnan(v) or (math.isinf(v) and not self.allow_inf):
            self.fail(f"{value!r} is not a finite number" + (f" ({self.what})" if self.what else ""), param, ctx)
        return super().convert(v, param, ctx)

    def _describe_range(self) -> str:
        text = super()._describe_range()
        return f"{text} ({self.what})" if self.what else text


def finite(rng: click.ParamType | None = None, **kw) -> Number:
    """The :class:`Number` with ``rng``'s bounds (a :class:`click.FloatRange`, ``click.FLOAT`` or None)."""
    if isinstance(rng, Number):
        return rng
    if isinstance(rng, click.FloatRange):
        return Number(rng.min, rng.max, rng.min_open, rng.max_open, rng.clamp, **kw)
    return Number(**kw)


#: Common quantities (each a :class:`Number`): a probability, a strictly positive and a
#: non-negative quantity, and any finite number.
PROBABILITY = Number(0.0, 1.0, what="a probability in [0, 1]")
POSITIVE = Number(0.0, min_open=True)
NONNEGATIVE = Number(0.0)
FINITE = Number()


def _finite_type(t: click.ParamType) -> click.ParamType:
    if isinstance(t, click.Tuple):
        return click.Tuple([_finite_type(x) for x in t.types])
    if isinstance(t, Number):
        return t
    if isinstance(t, click.FloatRange) or t is click.FLOAT:
        return finite(t)
    return t


def finite_types(cmd: click.Command) -> None:
    """Every float parameter of ``cmd`` (recursively through groups), tuples included, becomes a
    :class:`Number`: NaN and infinity are refused at parsing with the option named (exit 2).
    A parameter that must take infinity declares ``type=Number(..., allow_inf=True)`` itself."""
    if isinstance(cmd, click.Group):
        for sub in cmd.commands.values():
            finite_types(sub)
        return
    for p in cmd.params:
        p.type = _finite_type(p.type)


#: The one admissible range of the same-rotor correlation: rho = 1 makes R_theta singular
#: (Chen eq. 19) and an ADOP ~30x too optimistic.
RHO_RANGE = Number(0.0, 1.0, max_open=True)
#: Sweep-angle noise: > 0 (a prediction divides by it); simulators also take 0 (noise-free).
SIGMA_RANGE = Number(0.0, min_open=True)
SIGMA_RANGE_SIMULATION = Number(0.0)

_META = "layoutkit.alias."


def _alias_callback(dest: str, old: str, new: str, convert: Callable | None, note: bool = True):
    def cb(ctx, param, value):
        if value is None or ctx.get_parameter_source(param.name) in (ParameterSource.DEFAULT, None):
            return None
        if note:
            click.echo(f"note: {old} is deprecated; use {new}", err=True)
        ctx.meta[_META + dest] = convert(value) if convert is not None else value
        return None
    return cb


def _main_callback(dest: str, user_callback: Callable | None, required: bool = False):
    def cb(ctx, param, value):
        src = ctx.get_parameter_source(param.name)
        if src in (ParameterSource.DEFAULT, ParameterSource.DEFAULT_MAP, None) and (_META + dest) in ctx.meta:
            value = ctx.meta[_META + dest]
        if required and value is None and not ctx.resilient_parsing:
            raise click.MissingParameter(ctx=ctx, param=param)
        if user_callback is not None:
            value = user_callback(ctx, param, value)
        return value
    return cb


def explicit(ctx: click.Context, dest: str) -> bool:
    """Whether parameter ``dest`` was given (on the command line, the environment or through a deprecated
    alias) rather than left at its default: lets a command take a value from an input file when the user
    did not set it (``score LAYOUT`` takes the layout's recorded rho, half-angle, ...)."""
    src = ctx.get_parameter_source(dest)
    return src not in (ParameterSource.DEFAULT, ParameterSource.DEFAULT_MAP, None) or (_META + dest) in ctx.meta


def _unset_none(default) -> dict:
    """``{"default": default}``, or ``{}`` for None: click 8.5 takes an explicit ``default=None`` as a
    given default, so ``required=True`` was never checked (``calibrate`` without ``--stations`` went
    on with None and ended in a traceback, issue 29). Not given, the default is None all the same."""
    return {} if default is None else {"default": default}


def option(flag: str, dest: str, *, aliases: Iterable[str | tuple[str, Callable]] = (), callback=None,
           silent_aliases: Iterable[str] = (), **kw):
    """A click option ``flag`` delivering parameter ``dest``, with hidden deprecated ``aliases``.

    Each alias is a flag or ``(flag, convert)`` where ``convert`` maps the old spelling's value to
    the new one's (e.g. radians to arcseconds). Other keywords go to :func:`click.option`;
    ``required=True`` is checked after the aliases (an alias satisfies it). ``silent_aliases``:
    hidden spellings that are not deprecated and print nothing (an interface fixed elsewhere,
    e.g. ``import libsurvive --out DIR`` in issue 10, next to the visible ``--out-dir``).
    """
    required = bool(kw.pop("required", False))
    if kw.get("default", 0) is None:
        del kw["default"]                                      # see _unset_none
    aliases = tuple((a, True) for a in aliases) + tuple((a, False) for a in silent_aliases)
    alias_type = kw.get("type")
    alias_flag = kw.get("is_flag", False)
    alias_nargs = kw.get("nargs", 1)

    def deco(f):
        for a, note in aliases:
            old, convert = (a, None) if isinstance(a, str) else a
            name = "_alias_" + old.lstrip("-").replace("-", "_")
            extra = {"is_flag": True} if alias_flag else {"type": alias_type if convert is None else float,
                                                          "nargs": alias_nargs}
            f = click.option(old, name, hidden=True, expose_value=False, is_eager=True, default=None,
                             callback=_alias_callback(dest, old, flag, convert, note), **extra)(f)
        return click.option(flag, dest, callback=_main_callback(dest, callback, required and bool(aliases)),
                            required=required and not aliases, **kw)(f)
    return deco


class RegistryChoice(click.Choice):
    """A :class:`click.Choice` whose choices are the names of a registry, read when first needed.

    ``registry`` is a mapping (or iterable of names) or a ``"module:ATTR"`` string naming one; the
    string form keeps a heavy registry (the optimiser's methods) out of the CLI's import time.
    ``where(name, entry)`` keeps only some entries (e.g. protocols that have an encoder).
    The registry is looked up again on every access, so an entry registered later is offered too.
    """

    def __init__(self, registry, where: Callable | None = None, case_sensitive: bool = True):
        self.registry = registry
        self.where = where
        self.case_sensitive = case_sensitive

    def resolve(self):
        """The registry object itself."""
        reg = self.registry
        if isinstance(reg, str):
            mod, _, attr = reg.partition(":")
            reg = getattr(importlib.import_module(mod), attr)
        return reg

    @property
    def choices(self) -> tuple:  # type: ignore[override]
        reg = self.resolve()
        if self.where is None:
            return tuple(sorted(reg))
        return tuple(sorted(k for k in reg if self.where(k, reg[k])))

    @choices.setter
    def choices(self, value):  # click never sets it after __init__; keep the registry the source
        raise AttributeError("RegistryChoice.choices comes from its registry")


def registry_choice(registry, *, where: Callable | None = None) -> RegistryChoice:
    """A choice of a registry's names: a dict, an iterable of names, or ``"module:ATTR"`` (lazy)."""
    return RegistryChoice(registry, where=where)


# --------------------------------------------------------------------------- the quantities
def sigma_option(f=None, *, default: float | None = SIGMA_THETA_PAPER, help: str | None = None,
                 allow_zero: bool = False):
    """``--sigma-arcsec``: 1-sigma sweep-angle noise in arcsec; the command receives ``sigma`` in rad.

    ``default`` is in radians (None: no default, the command receives None); ``allow_zero``: a
    simulator or a solver of simulated frames, where 0 means noise-free (elsewhere sigma must be
    > 0: live predictions divide by it).
    Aliases: ``--sigma-theta-arcsec`` (render), ``--sigma-rad`` (fake-fpga, radians).
    """
    def to_rad(ctx, param, value):
        return None if value is None else float(value) * ARCSEC
    shown = False if default is None else f"{default / ARCSEC:.4f} = {default:.4g} rad"
    deco = option("--sigma-arcsec", "sigma", type=SIGMA_RANGE_SIMULATION if allow_zero else SIGMA_RANGE,
                  default=None if default is None else default / ARCSEC, show_default=shown, callback=to_rad,
                  aliases=("--sigma-theta-arcsec", ("--sigma-rad", lambda v: float(v) / ARCSEC)),
                  help=help or "Sweep-angle noise 1-sigma, arcsec (paper: 4.014e-5 rad = 8.28\"; Chen eq. 19).")
    return deco(f) if f is not None else deco


def rho_option(f=None, *, default: float = RHO_PAPER):
    """``--rho``: same-rotor angle correlation in [0, 1) (Chen eq. 19)."""
    deco = option("--rho", "rho", type=RHO_RANGE, default=default, show_default=True,
                  help="Same-rotor sweep-angle correlation, 0 <= rho < 1 (Chen eq. 19; paper 0.8717).")
    return deco(f) if f is not None else deco


def half_angle_option(f=None, *, default: float = 60.0):
    """``--half-angle-deg``: photodiode acceptance half-angle from its normal (alias
    ``--sensor-half-angle-deg``)."""
    deco = option("--half-angle-deg", "half_angle_deg", type=click.FloatRange(0.0, 90.0, min_open=True),
                  default=default, show_default=True, aliases=("--sensor-half-angle-deg",),
                  help="Photodiode acceptance half-angle from its normal, deg.")
    return deco(f) if f is not None else deco


def units_option(f=None, *, what: str = "the mesh file", flag: str = "--units", dest: str = "units"):
    """``--units``: length unit of an input file (m, cm, mm, in); another ``flag`` names the unit of
    another input (``--reference-units``)."""
    deco = click.option(flag, dest, type=click.Choice(LENGTH_UNIT_NAMES), default="m", show_default=True,
                        help=f"Length unit of {what}.")
    return deco(f) if f is not None else deco


def seed_option(f=None, *, default: int = 0):
    """``--seed``: the random seed (``numpy.random.default_rng(seed)``)."""
    deco = click.option("--seed", type=click.IntRange(0, 2**63 - 1), default=default, show_default=True,
                        help="Random seed (runs with the same seed are identical).")
    return deco(f) if f is not None else deco


def json_flag(f=None, *, help: str = "Print JSON to stdout instead of a table."):
    """``--json``: a flag; JSON goes to stdout. The command receives ``as_json``."""
    deco = click.option("--json", "as_json", is_flag=True, help=help)
    return deco(f) if f is not None else deco


def json_out_option(f=None, *, help: str = "Also write the JSON to this file ('-' = stdout)."):
    """``--json-out FILE``: write JSON to a file. The command receives ``json_out``."""
    deco = click.option("--json-out", "json_out", type=click.Path(dir_okay=False, allow_dash=True),
                        default=None, metavar="FILE", help=help)
    return deco(f) if f is not None else deco


def out_file_option(f=None, *, required: bool = True, help: str = "Output file.", default=None):
    """``--out FILE``: the command's output file. The command receives ``out``."""
    deco = click.option("--out", "out", type=click.Path(dir_okay=False), required=required, **_unset_none(default),
                        help=help)
    return deco(f) if f is not None else deco


def out_dir_option(f=None, *, required: bool = True, help: str = "Output folder.", default=None,
                   aliases: Iterable = (), out_alias: bool = False):
    """``--out-dir DIR``: the command's output folder. The command receives ``out_dir``.

    ``aliases``: deprecated old spellings (``("--out",)`` where a command used ``--out`` for a
    folder: a note on stderr). ``out_alias``: also accept ``--out DIR`` silently (hidden, no note)
    where another issue's interface spells the folder ``--out`` (``import libsurvive``, ``sweep``).
    """
    deco = option("--out-dir", "out_dir", type=click.Path(file_okay=False), required=required,
                  default=default, show_default=default is not None, help=help, aliases=aliases,
                  silent_aliases=("--out",) if out_alias else ())
    return deco(f) if f is not None else deco


def data_dir_option(f=None, *, help: str = "Input data folder."):
    """``--data DIR``: an existing input data folder (e.g. a public dataset). The command receives ``data_dir``."""
    deco = click.option("--data", "data_dir", type=click.Path(exists=True, file_okay=False), required=True, help=help)
    return deco(f) if f is not None else deco


def report_option(f=None, *, help: str = "Write a report folder (JSON + plots) here."):
    """``--report DIR``: a report folder. The command receives ``report_dir``."""
    deco = click.option("--report", "report_dir", type=click.Path(file_okay=False), default=None, help=help)
    return deco(f) if f is not None else deco


def layout_option(f=None, *, required: bool = True, help: str = "Layout JSON (docs/layout-format.md).",
                  multiple: bool = False):
    """``--layout FILE``. The command receives ``layout_path`` (a tuple with ``multiple``: the option
    may be given once per input, e.g. one layout per device of ``calibrate``)."""
    deco = click.option("--layout", "layout_path", type=click.Path(dir_okay=False), required=required,
                        help=help, multiple=multiple)
    return deco(f) if f is not None else deco


def envelope_option(f=None, *, required: bool = True, help: str = "Operating envelope TOML (docs/envelope.md)."):
    """``--envelope FILE``. The command receives ``envelope_path``."""
    deco = click.option("--envelope", "envelope_path", type=click.Path(dir_okay=False), required=required,
                        help=help)
    return deco(f) if f is not None else deco


def distance_m_option(f=None, *, default: float = 2.0, help: str = "Distance, m."):
    """``--distance-m`` (alias ``--distance``). The command receives ``distance_m``."""
    deco = option("--distance-m", "distance_m", type=click.FloatRange(min=0.0, min_open=True), default=default,
                  show_default=True, aliases=("--distance",), help=help)
    return deco(f) if f is not None else deco


def length_mm_option(flag: str, dest: str, *, default: float | None = None, required: bool = False,
                     allow_zero: bool = False, help: str = ""):
    """A length the user gives in millimetres (``flag`` ends in ``-mm``); the command receives ``dest``
    in metres (the one mm → m conversion, :data:`layoutkit.units.LENGTH_UNITS`). ``default`` is in
    mm, as ``--help`` shows it; ``allow_zero``: 0 is accepted (else the length must be > 0)."""
    def to_m(ctx, param, value):
        return None if value is None else float(value) * LENGTH_UNITS["mm"]

    return option(flag, dest, type=Number(0.0, min_open=not allow_zero), default=default,
                  show_default=default is not None, required=required, callback=to_m, help=help)


def refine_stations_option(f):
    """``--refine-stations``, ``--refine-from CAPTURE`` (repeatable) and ``--refine-calibration``:
    estimate the stations from the capture (and more captures of the same set-up) before solving
    (replay). The command receives ``refine_stations``, ``refine_from`` (a tuple of paths) and
    ``refine_calibration``."""
    f = click.option("--refine-calibration", is_flag=True,
                     help="With --refine-stations: also the observable calibration terms (on the Bitcraze dataset "
                          "they trade off against the station poses: 17 vs 9 mm RMS on a moving log, docs/live.md).")(f)
    f = click.option("--refine-from", "refine_from", multiple=True, type=click.Path(dir_okay=False),
                     help="Another capture of the same station set-up whose slow windows join --refine-stations "
                          "(repeatable; e.g. the static captures of a session for a moving one).")(f)
    return click.option("--refine-stations", is_flag=True,
                        help="Estimate the station poses (with --refine-calibration also the observable calibration "
                             "terms) from the capture's slow "
                             "windows seen by every station before solving; solve with them when they explain the "
                             "angles better; report how far each station moved, its 1-sigma, and whether the data "
                             "contradict the given set-up (summary 'station_refinement'; stations_refined.json in "
                             "--report for later --stations).")(f)


def imu_option(f):
    """``--imu/--no-imu``: with ``--filter ekf``, the IMU-aided filter on the capture's IMU samples (a
    Crazyflie log's own, or the ``imu.csv`` ``import cfusdlog`` wrote beside the capture). The command
    receives ``imu``: None (neither flag: use them when present), True (required) or False (the
    lighthouse-only filter)."""
    return click.option("--imu/--no-imu", "imu", default=None,
                        help="With --filter ekf: the IMU-aided filter on the capture's IMU samples (a Crazyflie log's "
                             "gyro/accelerometer events, or the imu.csv its import wrote beside the capture); "
                             "--no-imu: the lighthouse-only filter [default: the IMU when the capture has it].")(f)


def smooth_option(f):
    """``--smooth``: with ``--filter ekf`` and the IMU, replay's outputs from the offline fixed-lag
    smoother (:mod:`layoutkit.filter.smoother`). The command receives ``smooth`` (bool)."""
    return click.option("--smooth", "smooth", is_flag=True, default=False,
                        help="With --filter ekf and the IMU (replay only): the poses of the offline fixed-lag "
                             "smoother (each uses the sweeps of the next 1.5 s too; JSON lines delayed by up to 3 s "
                             "of data, marked \"smoothed\": true; poses in sweep gaps every 20 ms, \"event\": "
                             "\"gap\"); same ok limits as the filter.")(f)


def allow_odd_size_option(f=None):
    """``--allow-odd-size``: go on although the size of a mesh/layout says its ``--units`` are wrong."""
    deco = click.option("--allow-odd-size", is_flag=True,
                        help="Go on although the size says the length unit is probably wrong.")
    return deco(f) if f is not None else deco


def overwrite_option(f=None, *, what: str = "an existing capture"):
    """``--overwrite``: replace ``what`` explicitly (without it, an existing file is refused)."""
    deco = click.option("--overwrite", is_flag=True,
                        help=f"Replace {what} (without this flag it is refused and left untouched).")
    return deco(f) if f is not None else deco


def coverage_option(f=None):
    """``--coverage``: what "m lit" means with several stations (docs/optimize.md, coverage rules).
    The command receives ``coverage``."""
    deco = click.option("--coverage", "coverage", type=click.Choice(COVERAGE_CHOICES), default="any-station",
                        show_default=True,
                        help="Coverage rule: any-station (sensor lit by any station counts once), each-station "
                             "(every station alone sees --min-visible), joint (lit station-sensor pairs).")
    return deco(f) if f is not None else deco


def min_visible_option(f=None, *, default: int = 4, help: str = "Lit sensors needed for a pose to count as covered.",
                       aliases: Iterable = ()):
    """``--min-visible``: lit sensors a pose needs to count as covered. The command receives ``min_visible``.

    ``aliases``: old spellings (``("--min-lit",)`` in ``visibility``)."""
    deco = option("--min-visible", "min_visible", type=click.IntRange(min=1), default=default,
                  show_default=True, help=help, aliases=aliases)
    return deco(f) if f is not None else deco


def system_config_option(f=None):
    """``--system-config YAML``: a Crazyflie lighthouse system configuration (base-station geometry
    and calibration, cfclient's export). The command receives ``system_config``."""
    deco = click.option("--system-config", "system_config", type=click.Path(dir_okay=False), default=None,
                        metavar="YAML", help="Crazyflie lighthouse system config YAML (station geometry + calibration).")
    return deco(f) if f is not None else deco


def stations_option(f=None, *, required: bool = False,
                    help: str = "Stations JSON (station poses, calibration), e.g. from layoutkit import."):
    """``--stations FILE``: a stations JSON (station poses and calibration). The command receives
    ``stations_path``."""
    deco = click.option("--stations", "stations_path", type=click.Path(dir_okay=False),
                        required=required, metavar="FILE", help=help)
    return deco(f) if f is not None else deco


def ignore_calibration_option(f=None):
    """``--ignore-calibration``: solve through the ideal station model even when the stations JSON
    carries a calibration (the uncalibrated comparison). The command receives ``ignore_calibration``."""
    deco = click.option("--ignore-calibration", "ignore_calibration", is_flag=True,
                        help="Ignore the stations' calibration (ideal model; for comparison with the calibrated "
                             "solve, which is the default whenever --stations carries one).")
    return deco(f) if f is not None else deco


#: ``--filter`` choices: frame-by-frame PnP only, or the per-sweep EKF (layoutkit.filter).
FILTER_CHOICES = ("none", "ekf")


def filter_options(f):
    """``--filter ekf|none`` and the filter's tuning flags (SI units; docs/filter.md).

    The command receives ``filter_settings``: None for ``--filter none``, else a dict of
    :class:`layoutkit.filter.EkfConfig` keywords (``motion``, ``psd_rot`` rad²/s³, ``psd_pos`` m²/s³,
    ``gate_angle_p``, ``gate_sweep_p``, ``zupt``, ``constant_acceleration``, ``hit_timing``,
    ``model``) — the command adds sigma / rho from its own noise options.
    """
    import functools

    @functools.wraps(f)
    def wrapper(*args, filter_name, filter_motion, filter_psd_rot, filter_psd_pos, filter_gate_p, filter_zupt,
                filter_ca, filter_hit_timing, filter_model, **kwargs):
        kwargs["filter_settings"] = None if filter_name == "none" else {
            "motion": filter_motion, "psd_rot": filter_psd_rot, "psd_pos": filter_psd_pos, "gate_angle_p": filter_gate_p,
            "gate_sweep_p": filter_gate_p, "zupt": filter_zupt, "constant_acceleration": filter_ca,
            "hit_timing": filter_hit_timing, "model": filter_model}
        return f(*args, **kwargs)

    opts = [
        click.option("--filter", "filter_name", type=click.Choice(FILTER_CHOICES), default="none", show_default=True,
                     help="ekf: per-sweep error-state Kalman filter (one pose per sweep, with covariance); "
                          "none: frame-by-frame PnP only."),
        click.option("--filter-motion", "filter_motion", type=click.Choice(("adaptive", "fixed")), default="adaptive",
                     show_default=True,
                     help="Filter: adaptive = a bank of constant-velocity models from a resting to a swung or flown "
                          "body, mixed by their likelihoods (the process noise follows the motion, nothing to tune); "
                          "fixed = one model with --filter-psd-rot / --filter-psd-pos (needed by --filter-zupt, "
                          "--filter-ca)."),
        click.option("--filter-psd-rot", "filter_psd_rot", type=click.FloatRange(min=0.0), default=1e-6,
                     show_default=True, help="Filter (--filter-motion fixed): PSD of the white angular acceleration, "
                                             "rad^2/s^3."),
        click.option("--filter-psd-pos", "filter_psd_pos", type=click.FloatRange(min=0.0), default=1e-6,
                     show_default=True, help="Filter (--filter-motion fixed): PSD of the white linear acceleration, "
                                             "m^2/s^3."),
        click.option("--filter-gate-p", "filter_gate_p", type=click.FloatRange(0.0, 1.0, min_open=True, max_open=True),
                     default=1e-4, show_default=True,
                     help="Filter: false-rejection probability of the chi^2 outlier gates (per angle, per sweep)."),
        click.option("--filter-zupt", "filter_zupt", is_flag=True,
                     help="Filter: static detector with zero-velocity updates."),
        click.option("--filter-ca", "filter_ca", is_flag=True,
                     help="Filter: constant-acceleration motion model (default constant velocity)."),
        click.option("--filter-hit-timing/--no-filter-hit-timing", "filter_hit_timing", default=True, show_default=True,
                     help="Filter: each angle at its own hit time (sync + angle / rotor rate); off = at the sync time "
                          "(the simulator's model)."),
        click.option("--filter-model", "filter_model", type=click.Choice(("station", "plain")), default="station",
                     show_default=True,
                     help="Filter: forward model (station = each station's calibration when it has one)."),
    ]
    for o in reversed(opts):
        wrapper = o(wrapper)
    return wrapper


def protocol_option(f=None, *, default: str | None = "layoutkit", encodable: bool = False,
                    help: str = "Wire protocol (the registry in layoutkit.live.protocols)."):
    """``--protocol NAME``: a name of the protocol registry ``PROTOCOLS`` (``encodable``: of
    ``ENCODERS``, the entries layoutkit can emit). The command receives ``protocol``."""
    reg = "layoutkit.live.protocols:ENCODERS" if encodable else "layoutkit.live.protocols:PROTOCOLS"
    deco = click.option("--protocol", "protocol", type=registry_choice(reg),
                        default=default, show_default=default is not None, help=help)
    return deco(f) if f is not None else deco


def port_option(f=None, *, required: bool = True):
    """``--port``: a serial device, pty path or pyserial URL. The command receives ``port``."""
    deco = click.option("--port", "port", required=required, metavar="PORT",
                        help="Serial port: device or pty path, or a pyserial URL (socket://, loop://).")
    return deco(f) if f is not None else deco


def time_limit_option(f=None, *, help: str = "Wall-time budget, s."):
    """``--time-limit-s``: a wall-time budget in seconds. The command receives ``time_limit_s``."""
    deco = click.option("--time-limit-s", "time_limit_s", type=click.FloatRange(min=0.0, min_open=True),
                        default=None, help=help)
    return deco(f) if f is not None else deco


def camera_model_option(f=None, *, flags=("--camera-model",), required: bool = False,
                        help: str = "Camera model file: OpenCV YAML/XML (camera_matrix, distortion_coefficients, as "
                                    "`layoutkit camera calibrate` or OpenCV's calibration sample writes it) or our JSON."):
    """The camera model file (matrix + lens distortion; :mod:`layoutkit.io.camera`). ``flags``:
    ``camera attitude`` spells it ``--camera`` (issue 28), ``live``/``replay`` ``--camera-model``
    (their ``--camera`` is the attitude-CSV reference). The command receives ``camera_model``."""
    deco = click.option(*flags, "camera_model", type=click.Path(exists=True, dir_okay=False),
                        required=required, metavar="CAM.yml", help=help)
    return deco(f) if f is not None else deco


def corner_sigma_option(f=None, *, help: str = "Corner noise per coordinate, px [default: estimated from the residuals]."):
    """``--corner-sigma-px``: i.i.d. corner noise (px). The command receives ``corner_sigma_px``."""
    deco = click.option("--corner-sigma-px", "corner_sigma_px", type=POSITIVE, default=None, help=help)
    return deco(f) if f is not None else deco


def camera_options(f):
    """The live camera stream: ``--camera-device``, ``--focal-length-px``, ``--principal-point-px``,
    ``--camera-method``, ``--aspect-ratio``, ``--corner-sigma-px``, ``--camera-model`` (used by ``live``
    and ``replay``). The command receives ``camera_device, focal_length_px, principal_point_px,
    camera_method, aspect_ratio, corner_sigma_px, camera_model``."""
    opts = [
        click.option("--camera-device", "camera_device", default=None, metavar="INDEX|URL|FILE|DIR",
                     help="Camera stream beside the serial stream: an OpenCV device index, a stream URL, a video "
                          "file or an image folder (a camera capture folder plays at its recorded timing)."),
        click.option("--focal-length-px", "focal_length_px", type=click.FloatRange(min=0.0, min_open=True),
                     default=None, help="Camera focal length, px [default: the capture folder's camera.json]."),
        click.option("--principal-point-px", "principal_point_px", type=(float, float), default=None,
                     metavar="CX CY", help="Principal point, px [default: the image centre]."),
        click.option("--camera-method", "camera_method", type=registry_choice("layoutkit.camera.rectangle:RECTANGLE_SOLVERS"), default="ippe",
                     show_default=True, help="Rectangle-face attitude solver."),
        click.option("--aspect-ratio", "aspect_ratio", type=click.FloatRange(min=0.0, min_open=True), default=None,
                     help="Face aspect ratio L/W [default: the capture folder's camera.json, else 1]."),
        corner_sigma_option(),
        camera_model_option(help="Camera model file with the lens distortion (OpenCV YAML/XML or our JSON): corners "
                                 "are undistorted before the solve and the capture folder's camera.json records it "
                                 "[default: the capture folder's camera.json]."),
    ]
    for o in reversed(opts):
        f = o(f)
    return f


#: ``--solve`` choices: one pose per time window from all stations, or one per station frame.
SOLVE_MODES = ("joint", "per-station")


def solve_mode_option(f=None):
    """``--solve joint|per-station``; default (None): joint when several stations are known.
    The command receives ``solve_mode``."""
    deco = click.option("--solve", "solve_mode", type=click.Choice(SOLVE_MODES), default=None,
                        help="joint: one pose per 20 ms window from all stations (station 'joint'); per-station: "
                             "one pose per station frame. Default: joint when several stations are given.")
    return deco(f) if f is not None else deco


def motion_compensation_option(f=None, *, help: str | None = None):
    """``--motion-compensation/--no-motion-compensation`` (default None: the command decides, on for a
    joint solve). The command receives ``motion_compensation``."""
    deco = click.option("--motion-compensation/--no-motion-compensation", "motion_compensation", default=None,
                        help=help or ("--solve joint: each station's angles at their own time in the 20 ms window, "
                                      "the body at constant velocity (from the neighbouring poses); only windows "
                                      "whose motion moves the angles by > 0.25 sigma. Default on."))
    return deco(f) if f is not None else deco


def scheduler_option(f=None):
    """``--scheduler ADDRESS|synchronous``: where Dask tasks run (default: a LocalCluster here).

    The command receives ``scheduler`` (None = LocalCluster); see :func:`layoutkit.parallel.open_executor`.
    """
    deco = click.option("--scheduler", "scheduler", default=None, metavar="ADDRESS|synchronous",
                        help="Dask scheduler address (tcp://host:8786) of a running cluster, or 'synchronous' "
                             "(in-process, for debugging). Default: a LocalCluster on this machine.")
    return deco(f) if f is not None else deco


def workers_option(f=None):
    """``--workers N``: worker processes of the default LocalCluster. The command receives ``workers``."""
    deco = click.option("--workers", "workers", type=click.IntRange(min=1), default=None,
                        help="Worker processes of the local Dask cluster (default: the CPUs of this machine).")
    return deco(f) if f is not None else deco


# --------------------------------------------------------------------------- contradicting flags
class Conflict:
    """``a`` and ``b`` cannot both be given (``a`` may be ``"--flag=value"``: only with that value)."""

    def __init__(self, a: str, b: str, why: str = ""):
        self.a, self.b, self.why = a, b, why


class Requires:
    """``a`` means nothing without ``b``."""

    def __init__(self, a: str, b: str, why: str = ""):
        self.a, self.b, self.why = a, b, why


def _given(ctx: click.Context, spec: str):
    """Was ``spec`` (``--flag`` or ``--flag=value``) given on the command line? (value checked too)"""
    flag, _, want = spec.partition("=")
    for p in ctx.command.params:
        if flag in getattr(p, "opts", ()) or flag in getattr(p, "secondary_opts", ()):
            src = ctx.get_parameter_source(p.name)
            value = ctx.params.get(p.name)
            if want:
                return str(value) == want
            return src not in (ParameterSource.DEFAULT, ParameterSource.DEFAULT_MAP, None) and value not in (None, False, ())
    raise KeyError(f"{ctx.command.name} has no option {flag}")


def flag_rules(*rules):
    """Refuse contradicting or meaningless flag combinations before the command runs (exit 2,
    ``error:`` naming both flags). Each rule is a :class:`Conflict` or :class:`Requires`; put the
    decorator between ``@click.command`` (and its options) and the function."""
    import functools

    def deco(f):
        @functools.wraps(f)
        def wrapper(*args, **kwargs):
            ctx = click.get_current_context()
            for r in rules:
                why = f": {r.why}" if r.why else ""
                a, b = r.a.replace("=", " "), r.b.replace("=", " ")
                if isinstance(r, Conflict) and _given(ctx, r.a) and _given(ctx, r.b):
                    raise click.UsageError(f"{a} and {b} cannot be used together{why}", ctx)
                if isinstance(r, Requires) and _given(ctx, r.a) and not _given(ctx, r.b):
                    raise click.UsageError(f"{a} needs {b}{why}", ctx)
            return f(*args, **kwargs)
        return wrapper
    return deco
