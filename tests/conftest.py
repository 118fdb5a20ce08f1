"""Shared pytest fixtures."""
import os

import numpy as np
import pytest

os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")


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
