"""CLI fuzz: every numeric option of every command (found by walking ``layoutkit --help``, so a new
command is covered without a line here) given NaN, +-infinity, 0, a negative and a huge value.

Proof kind: exhaustive enumeration of the CLI's own parameter table against the contract of issue
29 — a value the option cannot honour ends with exit 2 and one ``error:`` line naming the option;
never a traceback; NaN and infinity are never accepted (unless an option documents infinity).
"""
from __future__ import annotations

import math

import click
import pytest
from click.testing import CliRunner

from cli_walk import leaf_commands
from layoutkit.cli import main
from layoutkit.cli.options import Number

BAD = ("nan", "inf", "-inf", "NaN", "+inf")
EDGE = ("0", "-1", "1e300")


def _numeric(t) -> bool:
    if isinstance(t, click.Tuple):
        return any(_numeric(x) for x in t.types)
    return isinstance(t, (click.types.FloatParamType, click.types.IntParamType))


def _cases():
    for path, cmd in leaf_commands():
        for p in cmd.params:
            if isinstance(p, click.Option) and _numeric(p.type) and p.opts:
                yield pytest.param(path, cmd, p, id=" ".join(path) + " " + p.opts[0])


CASES = list(_cases())


def _args(p, value):
    n = p.nargs if p.nargs > 0 else 1
    return [p.opts[0], *([value] * n)]


def test_every_command_has_been_enumerated():
    names = {" ".join(path) for path, _ in leaf_commands()}
    assert {"optimize", "score", "dop", "simulate", "fake-fpga", "replay", "live", "study chen2024"} <= names
    assert len(CASES) > 100  # commands x numeric options (134 when this test was written)


def test_every_float_option_is_a_finite_number():
    """The one boundary: no float parameter escapes :class:`Number` (a new command included)."""
    plain = []
    for path, cmd in leaf_commands():
        for p in cmd.params:
            types = p.type.types if isinstance(p.type, click.Tuple) else [p.type]
            plain += [f"{' '.join(path)} {p.name}" for t in types
                      if isinstance(t, click.types.FloatParamType) and not isinstance(t, Number)]
    assert plain == []


@pytest.mark.parametrize("path, cmd, p", CASES)
def test_nan_and_infinity_refused_with_the_option_named(path, cmd, p):
    runner = CliRunner()
    for value in BAD:
        if isinstance(p.type, Number) and p.type.allow_inf and "inf" in value.lower():
            continue
        r = runner.invoke(main, [*path, *_args(p, value)])
        assert r.exit_code == 2, (value, r.output)
        assert r.exception is None or isinstance(r.exception, SystemExit), r.exception
        assert "error:" in r.output and p.opts[0] in r.output, (value, r.output)
        assert "Traceback" not in r.output


@pytest.mark.parametrize("path, cmd, p", CASES)
def test_edge_values_refused_by_name_or_accepted_as_numbers(path, cmd, p):
    """0, -1 and 1e300: either the parser refuses them naming the option (exit 2), or the value the
    command receives is a finite number (the command's own checks then decide, see the run-level
    checks in the other tests)."""
    runner = CliRunner()
    for value in EDGE:
        ctx = click.Context(cmd, info_name=cmd.name)
        try:
            got = p.process_value(ctx, p.type_cast_value(ctx, [value] * p.nargs if p.nargs > 1 else value))
        except click.BadParameter:
            r = runner.invoke(main, [*path, *_args(p, value)])
            assert r.exit_code == 2 and "error:" in r.output and p.opts[0] in r.output, (value, r.output)
            continue
        vals = got if isinstance(got, tuple) else (got,)
        assert all(v is None or math.isfinite(v) for v in vals), (value, got)
