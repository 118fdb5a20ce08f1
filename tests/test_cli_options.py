"""One spelling per quantity across the whole CLI (issue 9, item 1).

Walks EVERY command and subcommand registered on ``layoutkit.cli.main`` at test time (recursively
through groups, so commands added later are covered) and checks the rules of
``layoutkit/cli/options.py`` against tables written here independently of that module:

(a) no two visible flag names for one quantity (a synonym table), and the one name is the
    canonical one; ``--out`` is never a folder, ``--out-dir``/``--report`` never a file;
(b) every ``--rho`` rejects 1.0 (rho = 1 makes R_theta singular, Chen eq. 19) and defaults to the
    paper's value;
(c) ``--json`` is always a flag;
(d) a choice that names an algorithm or protocol is exactly its registry (no copied list).

Then the deprecated aliases: each still works, prints one deprecation line on stderr and gives
the same parsed value as the new spelling (with the unit conversion where the unit changed), and
one end-to-end run on an old spelling produces byte-identical output to the new one.
Kind of proof: structural walk of the real click tree plus real parses and runs of the commands.

A new command complies by taking its quantities from ``layoutkit/cli/options.py``; where another
issue spells an output folder ``--out DIR``, use ``out_dir_option(out_alias=True)`` (visible
``--out-dir``, ``--out`` accepted quietly).
"""
from __future__ import annotations

import importlib
import json
import math
from pathlib import Path

import click
import pytest
from click.testing import CliRunner

from layoutkit.cli import main
from layoutkit.units import ARCSEC, RHO_PAPER, SIGMA_THETA_PAPER

REPO = Path(__file__).resolve().parents[1]
LAYOUT = str(REPO / "models" / "chen_target.layout.json")
MESH = str(REPO / "models" / "chen_target.stl")

# quantity -> (the one visible spelling, every spelling seen or plausible for it)
SYNONYMS = {
    "sigma": ("--sigma-arcsec", {"--sigma-arcsec", "--sigma-theta-arcsec", "--sigma-rad", "--sigma", "--sigma-theta",
                                 "--sigma-deg", "--noise-arcsec", "--angle-noise", "--sigma-theta-rad"}),
    "rho": ("--rho", {"--rho", "--correlation", "--rho-same-rotor", "--same-rotor-rho"}),
    "half-angle": ("--half-angle-deg", {"--half-angle-deg", "--sensor-half-angle-deg", "--half-angle",
                                        "--acceptance-deg", "--acceptance-half-angle-deg", "--cone-half-angle-deg"}),
    "distance": ("--distance-m", {"--distance-m", "--distance", "--dist", "--dist-m", "--station-distance"}),
    "seed": ("--seed", {"--seed", "--random-seed", "--rng-seed"}),
    "units": ("--units", {"--units", "--unit", "--mesh-units", "--length-unit", "--length-units"}),
    "json-as-path": ("--json-out", {"--json-out", "--json-path", "--json-file", "--out-json", "--write-json"}),
    "out-as-folder": ("--out-dir", {"--out-dir", "--output-dir", "--outdir", "--output-folder", "--out-folder"}),
    "layout": ("--layout", {"--layout", "--layout-json", "--layout-file"}),
    "envelope": ("--envelope", {"--envelope", "--envelope-toml", "--envelope-file"}),
    "time-limit": ("--time-limit-s", {"--time-limit-s", "--time-limit", "--timeout-s", "--time-budget"}),
    "min-lit": ("--min-visible", {"--min-visible", "--min-lit", "--min-sensors", "--min-lit-sensors"}),
}
# parameter name a command receives -> the flag that must deliver it
DEST_FLAG = {"min_visible": "--min-visible", "sigma": "--sigma-arcsec", "rho": "--rho", "half_angle_deg": "--half-angle-deg",
             "distance_m": "--distance-m", "out_dir": "--out-dir", "json_out": "--json-out", "as_json": "--json"}
# registries a choice may come from (imported by the test, not through the CLI)
REGISTRIES = {
    "layoutkit.live.protocols:PROTOCOLS": ("layoutkit.live.protocols", "PROTOCOLS"),
    "layoutkit.live.protocols:ENCODERS": ("layoutkit.live.protocols", "ENCODERS"),
    "layoutkit.optimize:METHODS": ("layoutkit.optimize", "METHODS"),
    "layoutkit.camera.rectangle:RECTANGLE_SOLVERS": ("layoutkit.camera", "RECTANGLE_SOLVERS"),
    "layoutkit.pnp:PNP_SOLVERS": ("layoutkit.pnp", "PNP_SOLVERS"),
    "layoutkit.camera.calibration:DISTORTION_MODELS": ("layoutkit.camera.calibration", "DISTORTION_MODELS"),
}
# flags whose choices name pluggable algorithms or protocols: they must come from a registry
REGISTRY_FLAGS = {"--method", "--solver", "--protocol", "--camera-method", "--rectangle-method"}
# commands that draw random numbers: they take --seed
RANDOM_COMMANDS = {"simulate", "candidates", "optimize", "fake-fpga", "study chen2024", "study zhai2014", "demo"}


def _registry(spec):
    mod, attr = REGISTRIES[spec]
    return getattr(importlib.import_module(mod), attr)


def _walk(group=main, path=()):
    ctx = click.Context(group, info_name=" ".join(path) or "layoutkit")
    for name in group.list_commands(ctx):
        cmd = group.get_command(ctx, name)
        if cmd is None:
            continue
        yield path + (name,), cmd
        if isinstance(cmd, click.Group):
            yield from _walk(cmd, path + (name,))


COMMANDS = [(" ".join(p), c) for p, c in _walk()]
OPTIONS = [(name, cmd, p) for name, cmd in COMMANDS for p in cmd.params if isinstance(p, click.Option)]


def _visible_flags(cmd):
    return [(f, p) for p in cmd.params if isinstance(p, click.Option) and not p.hidden for f in p.opts + p.secondary_opts]


def test_walk_sees_the_known_commands():
    """The walker reaches nested subcommands (else every check below would pass vacuously)."""
    names = {n for n, _ in COMMANDS}
    assert {"dop", "simulate", "solve", "render", "optimize", "live", "replay", "fake-fpga", "visibility",
            "study chen2024", "study zhai2014", "camera-attitude", "mesh-info", "candidates", "demo"} <= names


@pytest.mark.parametrize("name,cmd", COMMANDS, ids=[n for n, _ in COMMANDS])
def test_one_spelling_per_quantity(name, cmd):
    """(a) at most one visible flag per quantity in a command, and it is the canonical spelling."""
    flags = _visible_flags(cmd)
    for quantity, (canonical, names) in SYNONYMS.items():
        seen = sorted({f for f, _ in flags if f in names})
        assert len(seen) <= 1, f"{name}: two names for {quantity}: {seen}"
        assert not seen or seen == [canonical], f"{name}: {quantity} is spelled {seen[0]}, expected {canonical}"
    for p in cmd.params:
        if isinstance(p, click.Option) and not p.hidden and p.name in DEST_FLAG:
            assert DEST_FLAG[p.name] in p.opts, f"{name}: parameter {p.name} comes from {p.opts}"


@pytest.mark.parametrize("name,cmd", COMMANDS, ids=[n for n, _ in COMMANDS])
def test_out_is_a_file_and_out_dir_a_folder(name, cmd):
    """(a) ``--out`` is a file; ``--out-dir``/``--report`` are folders (click.Path file_okay/dir_okay)."""
    for f, p in _visible_flags(cmd):
        if not isinstance(p.type, click.Path):
            continue
        if f == "--out":
            assert p.type.file_okay and not p.type.dir_okay, f"{name}: --out is a folder; use --out-dir"
        if f in ("--out-dir", "--report"):
            assert p.type.dir_okay and not p.type.file_okay, f"{name}: {f} is a file; use --out"


@pytest.mark.parametrize("name,cmd", COMMANDS, ids=[n for n, _ in COMMANDS])
def test_rho_range_excludes_one(name, cmd):
    """(b) every option delivering rho accepts 0 and 0.99, rejects 1.0, and defaults to 0.8717."""
    for p in cmd.params:
        if not isinstance(p, click.Option) or not ({"--rho"} & set(p.opts) or p.name == "rho"):
            continue
        ctx = click.Context(cmd)
        assert p.type.convert(0.0, p, ctx) == 0.0 and p.type.convert(0.99, p, ctx) == 0.99
        with pytest.raises(click.BadParameter):
            p.type.convert(1.0, p, ctx)
        assert p.default == RHO_PAPER, f"{name}: --rho defaults to {p.default}"


@pytest.mark.parametrize("name,cmd", COMMANDS, ids=[n for n, _ in COMMANDS])
def test_json_is_a_flag(name, cmd):
    """(c) ``--json`` never takes a value (a file is ``--json-out FILE``)."""
    for f, p in _visible_flags(cmd):
        if f == "--json":
            assert p.is_flag and p.count is False, f"{name}: --json takes a value"
        if f == "--json-out":
            assert not p.is_flag, f"{name}: --json-out must take a FILE"


@pytest.mark.parametrize("name,cmd", COMMANDS, ids=[n for n, _ in COMMANDS])
def test_choices_come_from_registries(name, cmd):
    """(d) algorithm/protocol choices are their registry's names; no plain Choice copies a registry."""
    from layoutkit.cli.options import RegistryChoice

    for p in cmd.params:
        if not isinstance(p, click.Option) or not isinstance(p.type, click.Choice):
            continue
        if isinstance(p.type, RegistryChoice):
            spec = p.type.registry
            assert spec in REGISTRIES, f"{name} {p.opts[0]}: unknown registry {spec!r}"
            reg = _registry(spec)
            keys = sorted(reg) if p.type.where is None else sorted(k for k in reg if p.type.where(k, reg[k]))
            assert list(p.type.choices) == keys and set(keys) <= set(reg)
            assert keys, f"{name} {p.opts[0]}: an empty choice"
            if p.default is not None:
                assert p.default in keys
            continue
        assert not (set(p.opts) & REGISTRY_FLAGS), f"{name} {p.opts[0]}: a copied list, not registry_choice(...)"
        for spec in REGISTRIES:
            common = set(p.type.choices) & set(_registry(spec))
            assert len(common) < 2, f"{name} {p.opts[0]}: choices {sorted(common)} copy {spec}"


def test_protocol_choices_agree_between_commands():
    """``--protocol`` is the same registry choice everywhere (it was free text in one command and a
    fixed list in another); fake-fpga offers the protocols that have an encoder."""
    reg = _registry("layoutkit.live.protocols:PROTOCOLS")
    for name in ("live", "replay"):
        opt = next(p for p in main.commands[name].params if p.name == "protocol")
        assert list(opt.type.choices) == sorted(reg)
    fake = next(p for p in main.commands["fake-fpga"].params if p.name == "protocol")
    assert list(fake.type.choices) == sorted(k for k, e in reg.items() if e.encoder is not None)
    assert "layoutkit" in fake.type.choices


def test_bad_protocol_is_rejected_by_name():
    r = CliRunner().invoke(main, ["replay", "x.lkcap", "--protocol", "nmea"])
    assert r.exit_code == 2 and "Invalid value for '--protocol'" in r.output and "layoutkit" in r.output


@pytest.mark.parametrize("name", sorted(RANDOM_COMMANDS))
def test_random_commands_take_a_seed(name):
    cmd = dict(COMMANDS)[name]
    assert any("--seed" in p.opts for p in cmd.params if isinstance(p, click.Option)), f"{name}: no --seed"


@pytest.mark.parametrize("name,cmd", COMMANDS, ids=[n for n, _ in COMMANDS])
def test_sigma_defaults_to_the_paper(name, cmd):
    for p in cmd.params:
        if isinstance(p, click.Option) and p.name == "sigma" and isinstance(p.default, (int, float)):  # click 8.5: an option without a default holds a sentinel
            assert math.isclose(p.default * ARCSEC, SIGMA_THETA_PAPER, rel_tol=1e-12)


@pytest.mark.parametrize("name,cmd", COMMANDS, ids=[n for n, _ in COMMANDS])
def test_short_help_reads_whole(name, cmd):
    """Item 4: the one-line help in ``layoutkit --help`` (80 columns) is not cut mid-sentence."""
    limit = 78 - 6 - max(len(n.split()[-1]) for n, _ in COMMANDS)  # click: width - 6 - longest name
    text = cmd.get_short_help_str(limit=10**6)
    assert text and not text.endswith("...") and len(text) <= limit, f"{name}: {text!r} ({len(text)} > {limit})"


def test_hidden_aliases_stay_out_of_help():
    out = CliRunner().invoke(main, ["render", "--help"]).output
    for old in ("--sigma-theta-arcsec", "--sensor-half-angle-deg", "--distance ", "--out ", "--sigma-rad"):
        assert old not in out
    assert "--out-dir" in out and "--distance-m" in out and "--half-angle-deg" in out


# ------------------------------------------------------------------------------------------ aliases
def _parse(path, args, capsys):
    """The parameters ``layoutkit <path> <args>`` parses to (real click parse, no run) and its stderr."""
    cmd = main
    for p in path.split():
        cmd = cmd.commands[p]
    capsys.readouterr()
    ctx = cmd.make_context(path, list(args))
    return ctx.params, capsys.readouterr().err


SIGMA_RAD = 4.014e-5
ALIASES = [  # (command, old args, new args, base args, old flag, new flag)
    ("fake-fpga", ["--sigma-rad", repr(SIGMA_RAD)], ["--sigma-arcsec", repr(SIGMA_RAD / ARCSEC)],
     ["--layout", LAYOUT], "--sigma-rad", "--sigma-arcsec"),
    ("dop", ["--sigma-rad", repr(SIGMA_RAD)], ["--sigma-arcsec", "8.279470"], ["--layout", LAYOUT],
     "--sigma-rad", "--sigma-arcsec"),
    ("render", ["--sigma-theta-arcsec", "8.8"], ["--sigma-arcsec", "8.8"], [MESH, "--out-dir", "d"],
     "--sigma-theta-arcsec", "--sigma-arcsec"),
    ("render", ["--sensor-half-angle-deg", "45"], ["--half-angle-deg", "45"], [MESH, "--out-dir", "d"],
     "--sensor-half-angle-deg", "--half-angle-deg"),
    ("render", ["--distance", "3.5"], ["--distance-m", "3.5"], [MESH, "--out-dir", "d"], "--distance", "--distance-m"),
    ("render", ["--out", "pics"], ["--out-dir", "pics"], [MESH], "--out", "--out-dir"),
    ("study chen2024", ["--out", "o"], ["--out-dir", "o"], [], "--out", "--out-dir"),
    ("study zhai2014", ["--out", "o"], ["--out-dir", "o"], [], "--out", "--out-dir"),
    ("demo", ["--out", "o"], ["--out-dir", "o"], [], "--out", "--out-dir"),
    ("visibility", ["--min-lit", "5"], ["--min-visible", "5"], [MESH, "--layout", LAYOUT, "--envelope", "e.toml"],
     "--min-lit", "--min-visible"),
    ("optimize", ["--sensor-half-angle-deg", "50"], ["--half-angle-deg", "50"],
     [MESH, "-k", "4", "--envelope", "e.toml", "--out", "l.json"], "--sensor-half-angle-deg", "--half-angle-deg"),
]


@pytest.mark.parametrize("path,old,new,base,old_flag,new_flag", ALIASES,
                         ids=[f"{a[0]} {a[4]}" for a in ALIASES])
def test_alias_gives_the_same_value_and_a_note(path, old, new, base, old_flag, new_flag, capsys):
    p_old, err_old = _parse(path, base + old, capsys)
    p_new, err_new = _parse(path, base + new, capsys)
    assert err_old.strip() == f"note: {old_flag} is deprecated; use {new_flag}"
    assert err_new == ""
    assert p_old.keys() == p_new.keys()
    for k in p_new:
        a, b = p_old[k], p_new[k]
        if isinstance(b, float):
            assert math.isclose(a, b, rel_tol=1e-6), (k, a, b)
        else:
            assert a == b, (k, a, b)


def test_sigma_rad_is_converted_exactly(capsys):
    """``--sigma-rad 4.014e-5`` == ``--sigma-arcsec 8.2795...``: the same radians to 1e-15."""
    p, _ = _parse("fake-fpga", ["--layout", LAYOUT, "--sigma-rad", "4.014e-5"], capsys)
    q, _ = _parse("fake-fpga", ["--layout", LAYOUT, "--sigma-arcsec", repr(4.014e-5 / ARCSEC)], capsys)
    assert math.isclose(p["sigma"], 4.014e-5, rel_tol=1e-15) and math.isclose(q["sigma"], p["sigma"], rel_tol=1e-15)


def test_mm_lengths_arrive_in_metres(capsys):
    """``--spacing-mm 7.5`` reaches the command as metres (7.5 / 1000, the unit table's factor);
    0 is refused where a length must be positive."""
    p, _ = _parse("candidates", [MESH, "--spacing-mm", "7.5", "--out", "c.json"], capsys)
    assert "spacing_mm" not in p and math.isclose(p["spacing"], 7.5e-3, rel_tol=1e-15)
    r = CliRunner().invoke(main, ["candidates", MESH, "--spacing-mm", "0", "--out", "c.json"])
    assert r.exit_code == 2 and "--spacing-mm" in r.output


def test_new_spelling_wins_over_alias(capsys):
    p, err = _parse("render", [MESH, "--out-dir", "new", "--out", "old"], capsys)
    assert p["out_dir"] == "new" and "deprecated" in err


def test_required_folder_is_still_required():
    r = CliRunner().invoke(main, ["render", MESH])
    assert r.exit_code == 2 and "Missing option '--out-dir'" in r.output


def test_old_json_path_form_says_what_to_do(tmp_path):
    """``--json PATH`` cannot stay (``--json`` is a flag now): the usage error names ``--json-out``."""
    r = CliRunner().invoke(main, ["visibility", MESH, "--layout", LAYOUT, "--envelope", "e.toml",
                                  "--json", str(tmp_path / "v.json")])
    assert r.exit_code == 2 and "--json-out FILE" in r.output


def test_fake_fpga_old_sigma_spelling_end_to_end(tmp_path):
    """End to end on the old spelling: ``--sigma-rad`` writes the same capture bytes as the
    equivalent ``--sigma-arcsec`` (same seed), with the note on stderr only."""
    caps = []
    for k, args in enumerate((["--sigma-rad", "6e-5"], ["--sigma-arcsec", repr(6e-5 / ARCSEC)])):
        cap = tmp_path / f"c{k}.lkcap"
        r = CliRunner().invoke(main, ["fake-fpga", "--layout", LAYOUT, "--out", str(cap), "--duration", "0.5",
                                      "--seed", "4", "--json", *args])
        assert r.exit_code == 0, r.output
        assert json.loads(r.stdout)["frames_sent"] > 0
        assert ("note: --sigma-rad is deprecated; use --sigma-arcsec" in r.stderr) == (k == 0)
        caps.append(cap.read_bytes())
    assert caps[0] == caps[1]


def test_dop_old_sigma_spelling_end_to_end():
    """``dop --sigma-rad`` predicts the same precision as ``--sigma-arcsec`` (Chen eq. 24 at one pose)."""
    base = ["dop", "--layout", LAYOUT, "--rotvec-deg", "180", "0", "0", "--translation-m", "0.1", "0.2", "2", "--json"]
    a = CliRunner().invoke(main, base + ["--sigma-rad", "4.014e-5"])
    b = CliRunner().invoke(main, base + ["--sigma-arcsec", repr(4.014e-5 / ARCSEC)])
    assert a.exit_code == b.exit_code == 0, a.output + b.output
    ja, jb = json.loads(a.stdout), json.loads(b.stdout)
    assert ja["n_lit"] >= 4
    assert math.isclose(ja["predicted_sigma_rot_deg"], jb["predicted_sigma_rot_deg"], rel_tol=1e-12)
    assert math.isclose(ja["predicted_sigma_rot_deg"], ja["adop_deg_per_rad"] * 4.014e-5, rel_tol=1e-12)


@pytest.mark.parametrize("path", ["import libsurvive", "import cfusdlog"])
def test_issue10_out_dir_interface_still_parses(path, capsys):
    """Issue 10 fixes ``import libsurvive|cfusdlog ... --out DIR``: it parses to the same folder as
    the visible ``--out-dir DIR``, with no deprecation note (a silent alias, not an exception to
    the convention)."""
    p_old, err = _parse(path, ["input.rec", "--out", "D"], capsys)
    p_new, _ = _parse(path, ["input.rec", "--out-dir", "D"], capsys)
    assert p_old == p_new and p_new["out_dir"] == "D" and err == ""


def test_silent_out_alias_for_fixed_interfaces():
    """``out_dir_option(out_alias=True)``: visible ``--out-dir``, and ``--out DIR`` (an interface
    fixed by another issue, e.g. ``import libsurvive --out DIR``) accepted quietly, same value."""
    from layoutkit.cli.options import out_dir_option

    @click.command()
    @out_dir_option(out_alias=True)
    def cmd(out_dir):
        click.echo(out_dir)

    runner = CliRunner()
    a, b = runner.invoke(cmd, ["--out", "D"]), runner.invoke(cmd, ["--out-dir", "D"])
    assert a.exit_code == b.exit_code == 0 and a.stdout == b.stdout == "D\n" and a.stderr == ""
    assert "--out " not in runner.invoke(cmd, ["--help"]).output
    assert "Missing option '--out-dir'" in runner.invoke(cmd, []).output
