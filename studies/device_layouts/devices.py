"""Real device layouts from the libsurvive recordings, their hulls and the envelopes they are used in.

Each libsurvive recording carries, per tracked object, a ``CONFIG`` line with the device's own photodiode
layout (``lighthouse_config.modelPoints`` / ``modelNormals``): what Valve/HTC shipped. We read it through
``layoutkit.importers.libsurvive`` (the same path as ``layoutkit import libsurvive``, which writes it as
``<device>/layout.json``), take the convex hull of the sensor positions as the mesh (a stand-in for the
housing: every sensor lies on it), and describe how the device is used as an envelope:

- ``front``: the device's front axis in its body frame — the mean of its sensor normals (a headset's
  visor, a tracker's dome); the station sees the device from within ±``half_angle_deg`` (90°: the whole
  front hemisphere) of that axis, from 1–3 m, inside a 30° cone about the station's boresight, one LH1
  station (the issue's set-up);
- ``recording``: the recording's own stations (``<recording>.json``, libsurvive's calibrated station poses)
  and the device where libsurvive saw it (the median of its ``POSE`` lines, ±0.5 m in range), with the same
  ±90° attitude cone about the recorded attitude — "each station setup of the recording".
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

DATA = Path("/work/shared/data/libsurvive")

#: (label, recording, device) of the devices studied; the first two are the issue's must-show pair
DEVICES = (
    ("Vive headset (HMD, 32 sensors)", "lh1_test_cal_first4s.rec.gz", "HMD"),
    ("Vive tracker (WM0, 22 sensors)", "tracker-bad-tracking.rec.gz", "WM0"),
    ("Index headset (T20, 32 sensors)", "haagh-tracking2.rec.gz", "T20"),
    ("Index controller (Knuckles EV3.0 right, T20)", "lh1_test_cal_first4s.rec.gz", "T20"),
)


@dataclass(frozen=True)
class Device:
    """label, recording path, device name; layout (the shipped one, body frame, m); hull (trimesh, m);
    front (3,) unit body axis; poses (R (Q, 3, 3), t (Q, 3)) libsurvive's own solution of the device
    in the recording's world frame (may be empty); stations (the recording's, may be empty)."""

    label: str
    recording: str
    name: str
    layout: object
    hull: object
    front: np.ndarray
    poses: tuple
    stations: tuple


def load_device(label, recording, name, data=DATA) -> Device:
    """The shipped layout of device ``name`` in ``recording`` (its CONFIG line), its convex hull and axis."""
    import trimesh
    from layoutkit.importers.libsurvive import layout_of, read_recording

    path = Path(data) / recording
    rec = read_recording(path)
    lay = layout_of(rec, name)
    hull = trimesh.convex.convex_hull(lay.positions)
    m = lay.normals.mean(axis=0)
    front = m / np.linalg.norm(m)
    return Device(label, str(path), name, lay, hull, front, _recorded_poses(rec, name), _stations(path, name))


def _recorded_poses(rec, name):
    """libsurvive's POSE solution of the device as (R (Q, 3, 3), t (Q, 3)) (empty if none)."""
    from layoutkit.rotations import quaternion_to_matrix

    p = rec.poses.get(name)
    if not p:
        return np.zeros((0, 3, 3)), np.zeros((0, 3))
    arr = np.asarray(p, float)
    return quaternion_to_matrix(arr[:, 4:8], scalar_first=True), arr[:, 1:4]


def _stations(path, name):
    """The recording's stations with a known pose, as ``layoutkit import libsurvive`` writes them."""
    import tempfile

    from layoutkit.io.stations import read_stations
    from layoutkit.workflows.importers import import_libsurvive

    with tempfile.TemporaryDirectory() as d:
        summ = import_libsurvive(path, d, device=name)
        known = [s["pose_known"] for s in (summ.get("stations") or {}).get("stations", [])]
        st = read_stations(Path(d) / "stations.json") if summ.get("stations") else ()
    return tuple(s for s, k in zip(st, known) if k)


def _nominal_rotvec_deg(front, toward_world=(0.0, 0.0, -1.0)):
    """Rotation vector (deg) of the attitude that turns body axis ``front`` to ``toward_world``."""
    from scipy.spatial.transform import Rotation

    a = np.asarray(front, float) / np.linalg.norm(front)
    b = np.asarray(toward_world, float) / np.linalg.norm(toward_world)
    v = np.cross(a, b)
    s, c = np.linalg.norm(v), float(a @ b)
    if s < 1e-12:
        if c > 0:
            return (0.0, 0.0, 0.0)
        perp = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
        return tuple(np.degrees(math.pi * perp / np.linalg.norm(perp)))
    return tuple(np.degrees(Rotation.from_rotvec(v / s * math.atan2(s, c)).as_rotvec()))


def front_envelope(dev: Device, count=200, seed=13, half_angle_deg=90.0, range_m=(1.0, 3.0), cone_deg=30.0):
    """The issue's envelope: one LH1 station at the origin looking along +z, the device 1–3 m away in a
    30° cone about its boresight, its front axis towards the station within ±``half_angle_deg``."""
    from layoutkit.envelope import Envelope

    return Envelope.from_dict({
        "name": f"{dev.name} front ±{half_angle_deg:g}°", "count": int(count), "seed": int(seed),
        "range_m": list(range_m), "boresight_cone_deg": float(cone_deg),
        "attitude": {"kind": "cone", "nominal_rotvec_deg": list(_nominal_rotvec_deg(dev.front)),
                     "half_angle_deg": float(half_angle_deg)}})


#: housing stand-ins: the convex hull of the positions (the study's first mesh) or the tangent-cell housing
#: (``housing.py``: each sensor's Voronoi cell of the hull cut by its tangent plane)
HOUSINGS = ("hull", "tangent")


def with_housing(dev: Device, housing: str) -> Device:
    """``dev`` with its mesh replaced by the ``housing`` stand-in (``hull``: unchanged)."""
    import dataclasses

    if housing == "hull":
        return dev
    if housing != "tangent":
        raise ValueError(f"housing: expected one of {HOUSINGS}, got {housing!r}")
    from housing import tangent_cell_housing

    mesh, _ = tangent_cell_housing(dev.layout.positions, dev.layout.normals)
    return dataclasses.replace(dev, hull=mesh, label=f"{dev.label}, tangent-cell housing")


def mesh_path(folder: Path) -> Path:
    """The mesh of a device folder: ``housing.stl`` (the tangent-cell housing) if present, else ``hull.stl``."""
    folder = Path(folder)
    return folder / "housing.stl" if (folder / "housing.stl").exists() else folder / "hull.stl"


def folder_name(device: str, housing: str = "hull") -> str:
    """The results folder of a device (its CONFIG name, e.g. ``WM0``) on a housing: ``wm0``, ``wm0_tangent``."""
    return device.lower() + ("" if housing == "hull" else f"_{housing}")


def device_of_folder(folder: str) -> Device:
    """The device (on its housing) whose results live in ``folder`` (a :func:`folder_name`)."""
    name, _, housing = Path(folder).name.partition("_")
    found = [d for d in DEVICES if d[2] == name.upper()]
    if not found or (housing and housing not in HOUSINGS):
        raise ValueError(f"{folder}: not a device folder (expected one of "
                         f"{list(dict.fromkeys(folder_name(d[2], h) for d in DEVICES for h in HOUSINGS))})")
    label, rec, dn = found[0]
    return with_housing(load_device(label, rec, dn), housing or "hull")
