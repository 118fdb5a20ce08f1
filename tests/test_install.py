"""An installed wheel works away from the checkout: bundled models found as package data.

Proof kind: the real thing. pip builds a wheel of this checkout; a new virtual environment (no
system site packages) gets it; ``layoutkit demo`` then runs in a temporary folder, where neither
the checkout nor its ``models/`` is reachable, so the bundled mesh and envelope can only come from
the installed package. The independent reference for "every model is bundled" is the checkout's
own ``models/`` folder.

Three tests: the wheel installed alone (``--no-deps``) into a fresh environment that borrows the
third-party packages of the running one (a ``.pth`` line, which adds their folder but runs none of
its ``.pth`` files, so the checkout's editable hook stays out) carries every model and loads them
from outside the checkout (``slow``: in ``make test``); the same environment runs ``layoutkit demo``
outside the checkout, and pip installs the wheel with every dependency into a fresh environment and
runs the demo there (both ``install``: ``make test-install`` only — a fresh install compiles the
numba kernels, ~1-2 minutes of CPU each, and the full install fetches ~1 GB from pip's cache).
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
MODELS = REPO / "models"
DATA_SUFFIXES = {".stl", ".glb", ".ply", ".toml", ".json", ".png", ".csv"}


@pytest.fixture(scope="module")
def wheel(tmp_path_factory):
    """A wheel built from a clean copy of the sources (no stale ``build/`` of an earlier build)."""
    src = tmp_path_factory.mktemp("src")
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, src / name)
    skip = shutil.ignore_patterns("__pycache__", "*.pyc")
    shutil.copytree(REPO / "layoutkit", src / "layoutkit", symlinks=True, ignore=skip)
    shutil.copytree(MODELS, src / "models", ignore=skip)
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
                    "-w", str(out), str(src)], check=True, capture_output=True, text=True, cwd=out)
    (whl,) = out.glob("layoutkit-*.whl")
    return whl


def _fresh_venv(root: Path, with_pip: bool) -> Path:
    args = [sys.executable, "-m", "venv", str(root)] + ([] if with_pip else ["--without-pip"])
    subprocess.run(args, check=True, capture_output=True)
    return root / "bin" / "python"


def _site_packages(python: Path) -> Path:
    out = subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                         check=True, capture_output=True, text=True).stdout.strip()
    return Path(out)


def _env(python: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV", "PYTHONHOME")}
    env.update(PATH=f"{python.parent}:{env.get('PATH', '/usr/bin:/bin')}", PYVISTA_OFF_SCREEN="true", MPLBACKEND="Agg")
    return env


def _check_models_from_install(python: Path, work: Path):
    """layoutkit and its models resolve inside the fresh environment, and every data file of the
    checkout's models/ is there; a bundled mesh and layout load through the package."""
    code = ("import layoutkit, layoutkit.resources as r\n"
            "from layoutkit.mesh import load_mesh\n"
            "from layoutkit.layout import load_layout\n"
            "print(layoutkit.__file__); print(r.models_dir())\n"
            "print(len(load_mesh(r.model_path('chen_target.stl')).faces), "
            "len(load_layout(r.model_path('chen_target.layout.json')).positions))\n"
            "print('\\n'.join(sorted(str(p.relative_to(r.models_dir())) "
            "for p in r.models_dir().rglob('*') if p.is_file())))\n")
    out = subprocess.run([str(python), "-c", code], check=True, capture_output=True, text=True, cwd=work,
                         env=_env(python)).stdout.split("\n")
    site = _site_packages(python)
    assert Path(out[0]).is_relative_to(site), f"layoutkit imported from {out[0]}, not the fresh {site}"
    assert Path(out[1]).is_relative_to(site)
    from layoutkit.layout import load_layout
    from layoutkit.mesh import load_mesh

    assert out[2] == (f"{len(load_mesh(MODELS / 'chen_target.stl').faces)} "
                      f"{len(load_layout(MODELS / 'chen_target.layout.json').positions)}")  # same files as the checkout's
    bundled = {p for p in out[3:] if p}
    expected = {str(p.relative_to(MODELS)) for p in MODELS.rglob("*") if p.suffix in DATA_SUFFIXES}
    assert bundled == expected


def _run_demo_outside(python: Path, work: Path):
    """``layoutkit demo`` in ``work`` (outside the checkout) with the fresh environment."""
    r = subprocess.run([str(python.parent / "layoutkit"), "demo", "--out-dir", "demo"], capture_output=True,
                       text=True, cwd=work, env=_env(python), timeout=900)
    assert r.returncode == 0, r.stdout + r.stderr
    assert (work / "demo" / "optimize" / "layout.json").is_file()
    assert (work / "demo" / "chen2024").is_dir()
    # the shipped hand layout is found from the wheel too and compared over the same poses
    versus = json.loads((work / "demo" / "optimize" / "report" / "versus_shipped.json").read_text())
    assert versus["other"]["layout"].endswith("chen_target.layout.json") and "against the shipped" in r.stdout


@pytest.fixture(scope="module")
def lent_venv(wheel, tmp_path_factory):
    """A fresh venv holding the wheel alone; third-party packages lent from the running environment."""
    root = tmp_path_factory.mktemp("lent")
    python = _fresh_venv(root / "venv", with_pip=False)
    subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps", "-q", str(wheel)],
                   check=True, capture_output=True, text=True)
    # the running environment's third-party packages, without its .pth hooks (the editable layoutkit)
    (_site_packages(python) / "_lent_dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    return python


@pytest.mark.slow
def test_wheel_carries_the_models(lent_venv, tmp_path):
    _check_models_from_install(lent_venv, tmp_path)


@pytest.mark.slow
@pytest.mark.install
def test_wheel_runs_demo_outside_checkout(lent_venv, tmp_path):
    _run_demo_outside(lent_venv, tmp_path)


@pytest.mark.slow
@pytest.mark.install
def test_wheel_with_dependencies_in_fresh_venv(wheel, tmp_path):
    python = _fresh_venv(tmp_path / "venv", with_pip=True)
    r = subprocess.run([str(python), "-m", "pip", "install", "-q", str(wheel)], capture_output=True, text=True)
    if r.returncode != 0 and "Could not find a version" in r.stderr:
        pytest.skip(f"dependencies not installable here (no index or cache): {r.stderr.strip()[-300:]}")
    assert r.returncode == 0, r.stderr
    _check_models_from_install(python, tmp_path)
    _run_demo_outside(python, tmp_path)
