"""Every required option of every command is required (issue 29: ``calibrate FRAMES --layout L
--out-dir D`` without ``--stations`` went on with None and ended in a TypeError traceback; click 8.5
takes an explicit ``default=None`` as a given default and skips the required check).

Proof kind: exhaustive enumeration of the CLI's own parameter table (a new command or option is
covered without a line here): each required option left out, every other required parameter given
a value its type accepts, must end with exit 2 and click's "Missing option" naming that option.
"""
from __future__ import annotations

import click
import pytest
from click.testing import CliRunner

from cli_walk import leaf_commands
from layoutkit.cli import main


def _value(p, tmp_path) -> list[str]:
    """A value the parameter's type parses (a real file or folder for paths)."""
    t = p.type
    if isinstance(t, click.Path):
        if t.file_okay:
            f = tmp_path / "some_file"
            f.write_text("x\n")
            return [str(f)]
        d = tmp_path / "some_dir"
        d.mkdir(exist_ok=True)
        return [str(d)]
    if isinstance(t, click.Choice):
        return [str(t.choices[0])]
    if isinstance(t, (click.types.IntParamType, click.types.FloatParamType)):
        lo = getattr(t, "min", None)
        return [str(int(lo) + 1 if lo is not None else 1)]
    return ["x"]


CASES = [pytest.param(path, cmd, p, id=" ".join(path) + " " + p.opts[0])
         for path, cmd in leaf_commands() for p in cmd.params
         if isinstance(p, click.Option) and p.required]


def test_the_enumeration_sees_the_reported_case():
    assert any(path == ("calibrate",) and p.opts[0] == "--stations" for path, _, p in (c.values for c in CASES))
    assert len(CASES) >= 15  # 20 required options when this test was written


@pytest.mark.parametrize("path, cmd, p", CASES)
def test_a_missing_required_option_is_refused_by_name(path, cmd, p, tmp_path):
    args = list(path)
    for q in cmd.params:
        if q is p or not q.required:
            continue
        v = _value(q, tmp_path)
        args += v if isinstance(q, click.Argument) else [q.opts[0], *v * max(q.nargs, 1)]
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 2, (args, r.output, r.exception)
    assert r.exception is None or isinstance(r.exception, SystemExit), r.exception
    assert "Missing option" in r.output and p.opts[0] in r.output, r.output
