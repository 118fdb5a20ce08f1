"""The package surface: every lazily exported name resolves, and importing the core pulls in no
heavy room (cvxpy, pyvista, serial, OpenCV, click, rich) — the house rule of docs/architecture."""
import subprocess
import sys

import layoutkit


def test_every_export_resolves():
    for name in layoutkit.__all__:
        assert getattr(layoutkit, name) is not None, name


def test_core_import_is_light():
    code = ("import sys, layoutkit, layoutkit.dop, layoutkit.pnp, layoutkit.lighthouse, layoutkit.noise; "
            "print(','.join(m for m in ('cvxpy', 'pyvista', 'vtk', 'serial', 'cv2', 'click', 'rich', 'trimesh') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == ""
