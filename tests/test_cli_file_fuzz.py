"""CLI fuzz over file arguments: every input file of every command, replaced by an empty file, a
binary blob and a truncated copy of a valid one; and every file with a length or angle unit by a
copy written in the wrong unit (millimetres for metres, degrees for radians).

Proof kind: fault injection through the real CLI (CliRunner, each case in a forked child with a
time limit) against issue 29's contract: never a traceback; an empty or binary input ends with
exit 2 and an ``error:`` line naming the file; a truncated one either does the same or runs (a
cut capture is a shorter capture) — and never hangs. The base invocations are the README tour's,
shrunk; a new command gets its row here (``test_every_command_has_a_file_fuzz_row`` fails until
it does). A wrong-unit file is refused (exit 2, ``error:`` naming the file) or accepted with a
``warning:`` naming it — never taken silently.
"""
from __future__ import annotations

import multiprocessing as mp
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from cli_walk import leaf_commands
from layoutkit.cli import main

REPO = Path(__file__).resolve().parents[1]
MODELS = REPO / "models"
DATA = Path(__file__).parent / "data"

#: command -> (argument template, the placeholders that are input files to corrupt)
ROWS = {
    "mesh-info": ("{mesh}", ["mesh"]),
    "candidates": ("{mesh} --spacing-mm 30 --out {tmp}/c.json", ["mesh"]),
    "visibility": ("{mesh} --layout {layout} --envelope {envelope}", ["mesh", "layout", "envelope"]),
    "dop": ("--layout {layout} --rotvec-deg 180 0 0 --translation-m 0.3 0.2 2", ["layout"]),
    "score": ("{layout} --envelope {envelope} --json", ["layout", "envelope"]),
    "simulate": ("--layout {layout} --frames 3 --out {tmp}/f.csv", ["layout"]),
    "solve": ("{frames} --layout {layout} --json", ["frames", "layout"]),
    "render": ("{mesh} --layout {layout} --out-dir {tmp}/r --views iso --size 160x120", ["mesh", "layout"]),
    "optimize": ("{mesh} --envelope {envelope} --sensors 8 --spacing-mm 30 --time-limit-s 3 --no-render "
                 "--method greedy --out {tmp}/l.json", ["mesh", "envelope"]),
    "fake-fpga": ("--layout {layout} --out {tmp}/x.lkcap --duration 0.2 --motion {truth}", ["layout", "truth"]),
    "replay": ("{capture} --layout {layout} --truth {truth} --json", ["capture", "layout", "truth"]),
    "import reference": ("{truth} --out {tmp}/ref.csv", ["truth"]),
    "import libsurvive": ("{survive} --out {tmp}/sv", ["survive"]),
    "import vive-config": ("{vive} --out {tmp}/v.json", ["vive"]),
    "import cfusdlog": ("{truth} --out {tmp}/cf", ["truth"]),
    "calibrate": ("{frames_st} --layout {layout} --stations {stations} --out-dir {tmp}/cal", ["frames_st", "stations"]),
    "camera-attitude": ("{corners} --focal-length-px 2133.3 --json", ["corners"]),
    "camera calibrate": ("{photo} {photo2} {photo3} --inner 9x6 --square-mm 25 --out {tmp}/cam.yml --json", ["photo"]),
    "camera attitude": ("{photo} --camera {camera_yml} --detect chessboard --no-picture --json", ["photo", "camera_yml"]),
    "validate": ("{layout} --envelope {envelope} --frames 200 --scheduler synchronous --json", ["envelope"]),
    "sweep": ("{sweep} --out-dir {tmp}/sw --scheduler synchronous --json", ["sweep"]),
}
# no input file (live: a port; study bitcraze-dataset: a folder — its bad files are listed as not used,
# tests/test_study_bitcraze_dataset.py::test_bad_files_in_the_folder_are_listed_not_fatal)
NOT_FILE_COMMANDS = {"demo", "live", "study chen2024", "study zhai2014", "study bitcraze-dataset"}


def _commands():
    return (" ".join(path) for path, _ in leaf_commands())


def test_every_command_has_a_file_fuzz_row():
    assert set(_commands()) - NOT_FILE_COMMANDS == set(ROWS)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """Valid inputs of every kind, made by the commands themselves."""
    d = tmp_path_factory.mktemp("valid")
    r = CliRunner()
    f = {"mesh": MODELS / "chen_target.stl", "layout": MODELS / "chen_target.layout.json"}
    env = d / "env.toml"
    env.write_text("count = 6\nseed = 3\nrange_m = [1.0, 2.0]\nboresight_cone_deg = 20.0\n[attitude]\nkind = \"cone\"\n"
                   "nominal_rotvec_deg = [180.0, 0.0, 0.0]\nhalf_angle_deg = 30.0\n"
                   "[[station]]\nid = \"A\"\nposition_m = [0.0, 0.0, 0.0]\nrotvec_deg = [0.0, 0.0, 0.0]\n")
    f["envelope"] = env
    assert r.invoke(main, ["simulate", "--layout", str(f["layout"]), "--frames", "8", "--out", str(d / "f.csv")]).exit_code == 0
    f["frames"] = d / "f.csv"
    res = r.invoke(main, ["fake-fpga", "--layout", str(f["layout"]), "--out", str(d / "c.lkcap"), "--truth",
                          str(d / "truth.csv"), "--duration", "0.3"])
    assert res.exit_code == 0, res.output
    f["capture"], f["truth"] = d / "c.lkcap", d / "truth.csv"
    f["survive"] = DATA / "libsurvive" / "lh1_test_cal_first4s.rec.gz"
    f["vive"] = d / "vive.json"
    f["vive"].write_text('{"lighthouse_config": {"modelPoints": [[0,0,0],[0.01,0,0],[0,0.01,0],[0,0,0.01]], '
                         '"modelNormals": [[0,0,1],[0,0,1],[0,0,1],[1,0,0]]}}')
    f["stations"] = d / "stations.json"
    f["stations"].write_text('{"stations": [{"id": "A", "kind": "lh1", "translation": [0, 0, 0], '
                             '"rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}]}')
    res = r.invoke(main, ["simulate", "--layout", str(f["layout"]), "--frames", "40", "--stations", str(f["stations"]),
                          "--out", str(d / "fs.csv")])
    assert res.exit_code == 0, res.output
    f["frames_st"] = d / "fs.csv"
    f["photo"], f["photo2"], f["photo3"] = (DATA / "camera" / n for n in ("left01.jpg", "left03.jpg", "left04.jpg"))
    f["camera_yml"] = DATA / "camera" / "left_intrinsics.yml"
    f["corners"] = d / "corners.csv"
    f["corners"].write_text("t,x1,y1,x2,y2,x3,y3,x4,y4\n0,100,100,200,100,200,200,100,200\n")
    sweep = d / "sweep.toml"
    shutil.copy(env, d / "envelope.toml")
    sweep.write_text(f'[base]\nmesh = "{MODELS / "chen_target.stl"}"\nenvelope = "envelope.toml"\nspacing_mm = 30.0\n'
                     'time_limit_s = 2\nmethod = "greedy"\n[axes]\nk = [5]\n')
    f["sweep"] = sweep
    return f


def _child(conn, args):
    try:
        r = CliRunner().invoke(main, args)
        exc = r.exception
        tb = None if exc is None or isinstance(exc, SystemExit) else f"{type(exc).__name__}: {exc}"
        conn.send((r.exit_code, r.output[-3000:], tb))
    except BaseException as exc:  # noqa: BLE001
        conn.send((-1, "", f"{type(exc).__name__}: {exc}"))


def _context():
    """A fork server that has imported the CLI but never run a compiled kernel: forking the test
    process itself aborts ("fork() called from a process already using GNU OpenMP") once an earlier
    test in it ran numba's parallel PnP kernel."""
    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload(["layoutkit.cli", __name__, *_HEAVY])
    return ctx


#: what the commands import inside their bodies (~3 s a child would pay again for each of ~190 cases):
#: imported once by the fork server; importing runs no compiled kernel, so no OpenMP runtime starts
_HEAVY = ["cvxpy", "cv2", "matplotlib.pyplot", "pyvista", "dask.distributed", "trimesh", "scipy.optimize",
          "scipy.spatial", "layoutkit.pnp_numba", "layoutkit.joint_numba", "layoutkit.filter._kernels_numba"]


def _invoke(args, timeout=90.0):
    ctx = _context()
    a, b = ctx.Pipe(duplex=False)
    p = ctx.Process(target=_child, args=(b, args))
    p.start()
    b.close()
    got = a.recv() if a.poll(timeout) else None
    p.join(2)
    if p.is_alive():
        p.kill()
        p.join()
    return got


def _corrupt(kind: str, src: Path, dst: Path) -> Path:
    dst = dst.with_suffix("".join(src.suffixes) or ".dat")
    if kind == "empty":
        dst.write_bytes(b"")
    elif kind == "binary":
        dst.write_bytes(np.random.default_rng(7).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    else:  # truncated: the first 40 % of a valid file
        data = src.read_bytes()
        dst.write_bytes(data[: max(1, int(0.4 * len(data)))])
    return dst


@pytest.mark.slow
@pytest.mark.parametrize("cmd", sorted(ROWS))
def test_base_invocation_works_on_valid_files(files, tmp_path, cmd):
    """Each row's command runs on the valid files (so a refusal below is the corrupt file's doing)."""
    template, _ = ROWS[cmd]
    got = _invoke(cmd.split() + template.format(**{k: str(v) for k, v in files.items()}, tmp=str(tmp_path)).split())
    assert got is not None and got[2] is None, got
    assert got[0] == 0 or cmd == "import cfusdlog", got  # a pose table is no microSD log: refused, see below
    if cmd == "import cfusdlog":
        assert got[0] == 2 and "error:" in got[1], got


CASES = [pytest.param(cmd, ph, kind, id=f"{cmd}-{ph}-{kind}")
         for cmd, (_, phs) in ROWS.items() for ph in phs for kind in ("empty", "binary", "truncated")]


def _wrong_unit(ph: str, src: Path, dst: Path) -> Path:
    """A copy of the valid file ``src`` in the unit a user gets wrong: lengths in mm read as m,
    sweep angles in degrees read as radians."""
    import csv
    import json

    dst = dst.with_suffix("".join(src.suffixes))
    if ph == "layout":
        d = json.loads(src.read_text())
        d["sensors"] = [s | {"position": [1000.0 * c for c in s["position"]]} for s in d["sensors"]]
        dst.write_text(json.dumps(d))
    elif ph == "mesh":
        import trimesh

        trimesh.load_mesh(src).apply_scale(1000.0).export(dst)
    elif ph == "envelope":
        dst.write_text(src.read_text().replace("range_m = [1.0, 2.0]", "range_m = [1000.0, 2000.0]"))
    else:  # a table: pose positions (truth) or sweep angles (frames) scaled
        lines = src.read_text().splitlines()
        notes = [ln for ln in lines if ln.startswith("#")]  # a run tie (io.runtie) stays as it was
        rows = list(csv.reader(ln for ln in lines if not ln.startswith("#")))
        head = rows[0]
        cols = ({"tx", "ty", "tz"} if ph == "truth" else {c for c in head if c.startswith("th_")})
        scale = 1000.0 if ph == "truth" else 180.0 / np.pi
        out = [head] + [[f"{float(v) * scale!r}" if c in cols and v not in ("", "nan") else v
                         for c, v in zip(head, r)] for r in rows[1:]]
        dst.write_text("\n".join(notes + [",".join(r) for r in out]) + "\n")
    return dst


#: the file arguments with a length or angle unit (the rest: pixels, raw bytes, recordings with their own)
UNIT_FILES = {"layout", "mesh", "envelope", "truth", "frames", "frames_st"}
UNIT_CASES = [pytest.param(cmd, ph, id=f"{cmd}-{ph}-wrong-unit")
              for cmd, (_, phs) in ROWS.items() for ph in phs if ph in UNIT_FILES and cmd != "import cfusdlog"]


@pytest.mark.slow
@pytest.mark.parametrize("cmd, ph", UNIT_CASES)
def test_wrong_unit_file_is_refused_or_said(files, tmp_path, cmd, ph):
    template, _ = ROWS[cmd]
    bad = _wrong_unit(ph, Path(files[ph]), tmp_path / f"unit_{ph}")
    sub = {**{k: str(v) for k, v in files.items()}, ph: str(bad), "tmp": str(tmp_path)}
    got = _invoke(cmd.split() + template.format(**sub).split())
    assert got is not None, f"{cmd} with a {ph} in the wrong unit did not end within 90 s"
    code, out, tb = got
    assert tb is None and "Traceback" not in out, (code, tb, out)
    said = [ln for ln in out.splitlines() if ln.startswith(("error:", "warning:")) and bad.name in ln]
    assert said and (code == 2 or code == 0 and said[0].startswith("warning:")), (code, out)


@pytest.mark.slow
@pytest.mark.parametrize("cmd, ph, kind", CASES)
def test_corrupt_input_file(files, tmp_path, cmd, ph, kind):
    template, _ = ROWS[cmd]
    bad = _corrupt(kind, Path(files[ph]), tmp_path / f"bad_{ph}")
    sub = {**{k: str(v) for k, v in files.items()}, ph: str(bad), "tmp": str(tmp_path)}
    args = cmd.split() + template.format(**sub).split()
    got = _invoke(args)
    assert got is not None, f"{cmd} with a {kind} {ph} did not end within 90 s"
    code, out, tb = got
    assert tb is None and "Traceback" not in out, (code, tb, out)
    if kind in ("empty", "binary") or code != 0:
        assert code == 2 and "error:" in out and bad.name in out, (code, out)
