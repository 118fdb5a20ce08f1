"""Bundled data files (the models of ``models/``) found from the installed package, editable or not.

The repository's ``models/`` folder is the one source of the bundled meshes, layouts, envelopes and
camera frames; ``layoutkit/models`` links to it and the wheel carries its data files as package
data (pyproject.toml ``[tool.setuptools.package-data]``), so the same call finds them in a checkout,
an editable install and a wheel installed anywhere (after trimesh's ``resources/``). Paths typed by
users (``models/chen_target.stl``) are ordinary files of the checkout and need none of this.
"""
from __future__ import annotations

from importlib.resources import files
from pathlib import Path

__all__ = ["model_path", "models_dir"]


def models_dir() -> Path:
    """Folder of the bundled models (a directory of the installed package)."""
    return Path(str(files("layoutkit") / "models"))


def model_path(name: str) -> Path:
    """Path of the bundled model file ``name`` (e.g. ``"chen_target.stl"``,
    ``"camera_frames/truth.csv"``); ``FileNotFoundError`` naming the file and the folder searched
    when this installation lacks it."""
    p = models_dir() / name
    if not p.is_file():
        raise FileNotFoundError(f"bundled model {name!r}: not found in {p.parent} (is layoutkit installed "
                                f"with its package data?)")
    return p
