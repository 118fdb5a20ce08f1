"""The Crazyflie system-configuration YAML owner (layoutkit.io.systemconfig): read ∘ write is the
identity on stations (world poses in layoutkit's station frame, rotor speed of the channel) and
calibrations, and a bad file is named in the error.

Proof kind: round trip through the file against the objects written, and the firmware's own
channel period table (CYCLE_PERIODS) for the rotor speed.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from layoutkit.io.systemconfig import (DECK_CLOCK_HZ, LH2_CYCLE_PERIODS, SystemConfig, read_system_config,
                                       write_system_config)
from layoutkit.lighthouse import Station, StationCalibration, SweepCalibration


def _config(system_type=2):
    rng = np.random.default_rng(3)
    st = {k: Station(id=str(k), rotation=Rotation.from_rotvec(rng.normal(size=3)).as_matrix(),
                     translation=rng.uniform(-3, 3, 3), kind="lh2" if system_type == 2 else "lh1")
          for k in (0, 1)}
    cal = {k: StationCalibration(tuple(SweepCalibration(*rng.uniform(-0.01, 0.01, 7)) for _ in range(2)), 100 + k)
           for k in (0, 1)}
    return SystemConfig(st, cal, system_type)


@pytest.mark.parametrize("system_type", [1, 2])
def test_write_then_read_gives_the_same_stations_and_calibrations(tmp_path, system_type):
    cfg = _config(system_type)
    path = tmp_path / "sys.yaml"
    write_system_config(path, cfg)
    back = read_system_config(path)
    assert back.system_type == system_type and back.source == str(path)
    assert sorted(back.stations) == [0, 1] and sorted(back.calibs) == [0, 1]
    for k in (0, 1):
        np.testing.assert_allclose(back.stations[k].rotation, cfg.stations[k].rotation, atol=1e-12)
        np.testing.assert_allclose(back.stations[k].translation, cfg.stations[k].translation, atol=1e-12)
        assert back.calibs[k] == cfg.calibs[k]
        assert back.stations[k].clock_hz == DECK_CLOCK_HZ
    if system_type == 2:  # channel k's rotor: one turn per CYCLE_PERIODS[k] deck ticks
        for k in (0, 1):
            assert back.stations[k].rotor_rpm == pytest.approx(60 * DECK_CLOCK_HZ / LH2_CYCLE_PERIODS[k])
    assert [s.id for s in back.station_list()] == ["0", "1"]
    assert read_system_config(back) is back  # an object passed on is not read again


def test_station_ids_must_index_the_stations(tmp_path):
    cfg = _config()
    path = tmp_path / "gap.yaml"
    write_system_config(path, SystemConfig({0: cfg.stations[0], 2: cfg.stations[1]}, {}, 2))
    with pytest.raises(ValueError, match=r"gap.yaml: base-station ids \[0, 2\] are not 0..k-1"):
        read_system_config(path).station_list()


def test_bad_entry_is_named(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("type: lighthouse_system_configuration\nversion: '1'\ngeos: {0: {origin: [0, 0]}}\n")
    with pytest.raises(ValueError, match=r"bad.yaml: bad geos/calibs entry"):
        read_system_config(path)
