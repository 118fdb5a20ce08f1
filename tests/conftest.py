"""Shared pytest fixtures, and the numba kernels compiled once before xdist's workers start."""
import os
import subprocess
import sys
import time
from pathlib import Path

# One BLAS thread per test process, set before numpy loads OpenBLAS here and inherited by the xdist
# workers and the processes tests start: the suite runs three workers on two cores, where OpenBLAS's
# second thread has no core and spins waiting for one. Measured on the calibration tests (scipy's
# dense least-squares reference, two optimisers on one problem) on the loaded 2-core machine: 42.6 s
# -> 22.8 s CPU, 77 s -> 37 s wall; one least_squares solve alone 35 s -> 0.7 s CPU.
for _var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np
import pytest

os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")


def pytest_configure(config):
    """With pytest-xdist workers (``-n N``, N >= 2), compile the kernels first in two processes
    (tests/_warm_kernels.py): in a fresh checkout both workers would otherwise compile the same
    kernels at the same time. A few seconds when the cache is there; skipped with -n 0, in the
    workers themselves, or with LAYOUTKIT_TEST_NO_WARM=1."""
    n = getattr(config.option, "numprocesses", None)
    if hasattr(config, "workerinput") or not n or os.environ.get("LAYOUTKIT_TEST_NO_WARM"):
        return
    t0 = time.monotonic()
    script = Path(__file__).with_name("_warm_kernels.py")
    procs = [subprocess.Popen([sys.executable, str(script), g], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                              text=True) for g in ("pose", "filter")]
    failed = [(g, p.communicate()[1][-400:]) for g, p in zip(("pose", "filter"), procs) if p.wait() != 0]
    for g, err in failed:  # the tests then compile what they need themselves (and fail where it is broken)
        config.issue_config_time_warning(pytest.PytestWarning(f"kernel warm-up '{g}' failed: {err}"), stacklevel=2)
    if time.monotonic() - t0 > 10:
        print(f"numba kernels compiled in {time.monotonic() - t0:.0f} s (tests/_warm_kernels.py)", file=sys.stderr)


#: tests/durations.json: seconds per test id, measured by a whole run of the suite with
#: ``LAYOUTKIT_TEST_DURATIONS=tests/durations.json`` (``make durations``); a test recorded at SLOW_S or
#: more is marked ``slow`` (``make test-fast`` leaves it out), and files run longest first, so the
#: workers (handed one test at a time: the Makefile's XDIST) do not end on one long file. A test not in the
#: file yet is not marked.
DURATIONS = Path(__file__).with_name("durations.json")
SLOW_S = 0.5
_measured: dict = {}


@pytest.hookimpl(tryfirst=True)  # before -m deselects by the marks
def pytest_collection_modifyitems(config, items):
    import json

    try:
        known = json.loads(DURATIONS.read_text())
    except (OSError, ValueError):
        return
    per_file: dict = {}
    for it in items:
        d = known.get(it.nodeid, 0.0)
        if d >= SLOW_S:
            it.add_marker(pytest.mark.slow)
        per_file[it.nodeid.split("::")[0]] = per_file.get(it.nodeid.split("::")[0], 0.0) + d
    order = {it.nodeid: k for k, it in enumerate(items)}
    items.sort(key=lambda it: (-per_file[it.nodeid.split("::")[0]], order[it.nodeid]))


@pytest.hookimpl(optionalhook=True)  # without pytest-xdist (-p no:xdist) there is no such hook
def pytest_xdist_make_scheduler(config, log):
    """``--dist loadgroup`` (the Makefile's): tests handed out one at a time, except that the tests of
    a module defining a module- or class-scoped fixture go to one worker together. Handed out singly,
    such a module's tests landed on every worker and each built the fixture again (the camera bench
    rendered on three workers). xdist's own loadgroup reads ``xdist_group`` marks through a node
    attribute pytest 9 no longer has, so it silently spread the groups; this scheduler groups by
    module path, known in the controller from the test files themselves."""
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadScopeScheduling

    grouped = _modules_with_shared_fixtures(Path(__file__).parent)

    class ModuleFixtureScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid):
            module = nodeid.split("::", 1)[0]
            return module if module in grouped else nodeid

    return ModuleFixtureScheduling(config, log)


def _modules_with_shared_fixtures(folder: Path) -> set:
    """``tests/test_X.py`` paths of the modules that define a ``@pytest.fixture(scope="module"|"class")``."""
    import ast

    out = set()
    for path in sorted(folder.glob("test_*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            for dec in getattr(node, "decorator_list", ()):
                if isinstance(dec, ast.Call) and any(
                        k.arg == "scope" and isinstance(k.value, ast.Constant) and k.value.value in ("module", "class")
                        for k in dec.keywords):
                    out.add(f"{folder.name}/{path.name}")
    return out


def pytest_runtest_logreport(report):
    if os.environ.get("LAYOUTKIT_TEST_DURATIONS"):
        _measured[report.nodeid] = _measured.get(report.nodeid, 0.0) + report.duration


def pytest_sessionfinish(session, exitstatus):
    out = os.environ.get("LAYOUTKIT_TEST_DURATIONS")
    if out and _measured and not hasattr(session.config, "workerinput"):
        import json

        from layoutkit.io.atomic import atomic_write_text

        atomic_write_text(out, json.dumps({k: round(v, 3) for k, v in sorted(_measured.items())}, indent=0) + "\n")


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


@pytest.fixture
def small_envelope(tmp_path):
    """A 30-pose Chen-like envelope TOML (one station, target 1–2 m away facing it); its path."""
    p = tmp_path / "env.toml"
    p.write_text("""count = 30
seed = 3
range_m = [1.0, 2.0]
boresight_cone_deg = 20.0
[attitude]
kind = "cone"
nominal_rotvec_deg = [180.0, 0.0, 0.0]
half_angle_deg = 30.0
""")
    return str(p)


@pytest.fixture(scope="session")
def libsurvive_dir():
    """Folder of the two real libsurvive sample recordings (tests/data/libsurvive, MIT)."""
    from pathlib import Path

    return Path(__file__).parent / "data" / "libsurvive"


@pytest.fixture(autouse=True)
def _figures_without_overlaps(monkeypatch):
    """Every matplotlib figure any test saves is checked for overlapping text and panels
    (:func:`layoutkit.io.figures.layout_problems`: bounding boxes of titles, labels, tick labels,
    legends, captions; a colour bar over a panel). Issue 29 item 6: every figure type a report or
    study writes is rendered by some test, so each one is checked here."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.figure

    from layoutkit.io.figures import layout_problems

    seen = []
    orig = matplotlib.figure.Figure.savefig

    def checking_savefig(self, fname, *a, **kw):
        problems = layout_problems(self)
        if problems:
            name = getattr(fname, "name", fname)
            title = self._suptitle.get_text() if self._suptitle is not None else (
                self.axes[0].get_title() if self.axes else "")
            seen.append(f"{name} ({title}): " + "; ".join(problems))
        return orig(self, fname, *a, **kw)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", checking_savefig)
    yield
    assert not seen, "figures with overlapping text or panels:\n" + "\n".join(seen)
