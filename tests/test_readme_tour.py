"""The README tour runs as written (issue 14, item 12).

Every command line of the README's "A tour" block is taken from README.md itself and run in a
fresh temporary folder (``models/`` linked in), with only run lengths shortened — the changes are
listed in SHORTEN and applied by exact text replacement, so a line that changes in the README and
no longer matches fails this test instead of being skipped. The pty pair (``fake-fpga ... &``,
then ``live --port /dev/pts/N``) runs for real: the device path the simulator prints is put in
place of ``/dev/pts/N``. Each line must exit 0 and print no traceback. The simulator and ``live`` run as
processes; the other lines run through click's test runner in this process (the same command; the
package imported once instead of per line).
"""
from __future__ import annotations

import contextlib
import os
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
EXE = [sys.executable, "-m", "layoutkit"]

#: (command, README text, test text): shorter runs, same commands and files.
SHORTEN = [
    ("optimize", "--spacing-mm 8", "--spacing-mm 14 --no-render"),
    ("optimize", "--time-limit-s 120", "--time-limit-s 10"),
    ("score", "--draws 5", "--draws 2 --poses 300"),
    ("render", "--out-dir out/pics/", "--out-dir out/pics/ --size 320x240 --grid-deg 15 --views iso"),
    ("simulate", "--frames 10000", "--frames 300"),
    ("fake-fpga", "--duration 600", "--duration 3"),
    ("fake-fpga", "--duration 60", "--duration 4 --wait-reader 60"),
    ("live", "--report out/val-live/", "--report out/val-live/ --duration 30 --idle-timeout 1.5"),
    ("chen2024", "--groups 50 --frames 3600", "--groups 2 --frames 30 --dynamic-seconds 1 --scheduler synchronous"),
    ("zhai2014", "study zhai2014", "study zhai2014 --quick"),
    ("sweep", "models/chen_sweep.toml", "models/chen_sweep_quick.toml --scheduler synchronous"),
    ("validate", "--frames 1000000", "--frames 3000 --scheduler synchronous"),
]


def tour_lines() -> list[str]:
    """The tour's command lines (continuations joined, comments and the `lk=` line dropped)."""
    text = (REPO / "README.md").read_text()
    block = text.split("## A tour", 1)[1].split("```bash", 1)[1].split("```", 1)[0]
    lines, cur = [], ""
    for raw in block.splitlines():
        cur += raw.rstrip()
        if cur.endswith("\\"):
            cur = cur[:-1] + " "
            continue
        if cur.strip().startswith("$lk "):
            lines.append(cur.strip())
        cur = ""
    return lines


def _shorten(line: str) -> str:
    for cmd, old, new in SHORTEN:
        if f" {cmd} " in f" {line} " and old in line:
            line = line.replace(old, new, 1)
    return line


def test_tour_block_is_paste_ready():
    """No bracketed optional arguments, no placeholder folders that nothing creates, no file written
    twice by different lines (the second fake-fpga overwrote truth.csv), every file it writes under
    out/ (it used to write 15 files into the repository root)."""
    lines = tour_lines()
    assert len(lines) >= 15
    assert not any(re.search(r"\[--", ln) for ln in lines)
    outs = [a for ln in lines for a in re.findall(r"--(?:out|out-dir|json-out|truth|record|report) (\S+)", ln)
            if "replay" not in ln and " live " not in f" {ln} "]
    assert len(outs) == len(set(outs)), outs
    writes = [a for ln in lines for a in re.findall(r"--(?:out|out-dir|json-out|record|report) (\S+)", ln)]
    assert writes and all(a.startswith("out/") for a in writes), writes
    assert "mkdir -p out" in (REPO / "README.md").read_text().split("## A tour", 1)[1].split("```", 2)[1]


def _group(line: str) -> str:
    """Which test runs a tour line: the lines of a group depend on each other's files."""
    w = shlex.split(line, comments=True)[1]
    return {"fake-fpga": "live", "replay": "live", "live": "live", "study": "studies",
            "camera-attitude": "studies"}.get(w, "design")


def _run_lines(lines, tmp_path):
    (tmp_path / "models").symlink_to(REPO / "models")
    (tmp_path / "out").mkdir()  # the tour's `mkdir -p out`
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    device = None
    for line in lines:
        cmd = _shorten(line)
        args = shlex.split(cmd, comments=True)
        background = args[-1] == "&"
        args = [a for a in args if a != "&"]
        assert args[0] == "$lk", line
        if device is not None and "/dev/pts/N" in args:
            args = [device[0] if a == "/dev/pts/N" else a for a in args]
        if background:
            p = subprocess.Popen(EXE + args[1:], cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True)
            first = p.stdout.readline().strip()
            assert first.startswith("device: "), (line, first, p.stderr.read() if p.poll() is not None else "")
            device = (first.split(": ", 1)[1], p)
            continue
        t0 = time.monotonic()
        if args[1] == "live":  # beside the simulator's process, with its signals and threads: a process too
            r = subprocess.run(EXE + args[1:], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
            assert r.returncode == 0 and "Traceback" not in r.stderr, (cmd, r.returncode, r.stdout[-800:],
                                                                       r.stderr[-1500:])
            _, err = device[1].communicate(timeout=60)
            assert device[1].returncode == 0, err
            assert (tmp_path / "out" / "cap.lkcap").stat().st_size > 0
            assert (tmp_path / "out" / "val-live" / "report.json").is_file()
        else:  # in this process (the same click command; no interpreter start and kernel loading per line)
            _invoke(args[1:], tmp_path, cmd)
        print(f"{time.monotonic() - t0:6.1f} s  {cmd}")


def _invoke(args, cwd, cmd):
    """``layoutkit ARGS`` run by click's test runner in ``cwd``: exit 0, no exception."""
    from click.testing import CliRunner

    from layoutkit.cli import main

    with contextlib.chdir(cwd):
        r = CliRunner().invoke(main, args)
    exc = None if isinstance(r.exception, SystemExit) else r.exception
    assert r.exit_code == 0 and exc is None and "Traceback" not in r.output, (cmd, r.exit_code, repr(exc),
                                                                               r.output[-1500:])


def test_every_shortening_applies():
    """Each SHORTEN entry matches a tour line (a README edit cannot silently drop a shortening)."""
    lines = tour_lines()
    for c, o, _ in SHORTEN:
        assert any(f" {c} " in f" {ln} " and o in ln for ln in lines), (c, o)


@pytest.mark.parametrize("group, files", [
    ("design", ["cands.json", "layout.json", "report/summary.json", "pics", "frames.csv"]),
    ("live", ["run.lkcap", "truth.csv", "val/report.json", "truth-live.csv", "cap.lkcap", "val-live/report.json"]),
    ("studies", ["groups.json"]),
])
@pytest.mark.slow
def test_readme_tour_runs(tmp_path, group, files):
    lines = [ln for ln in tour_lines() if _group(ln) == group]
    assert lines
    _run_lines(lines, tmp_path)
    for f in files:
        assert (tmp_path / "out" / f).exists(), f
    assert sorted(p.name for p in tmp_path.iterdir()) == ["models", "out"]  # nothing written outside out/
