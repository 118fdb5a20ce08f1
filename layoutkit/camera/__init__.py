"""Monocular camera room: rectangle-face attitude (Zhai et al. 2014), corner detection,
synthetic pinhole renders and camera input for the live mode (design §7, §8); real cameras:
lens distortion (``lens``), calibration from pattern photos (``calibration``), face attitude
through a lens with its predicted σ (``face``) and a face detector for photographs (``face_detect``).

``rectangle_attitude`` and ``euler_zyx`` are the public entry points (re-exported by
``layoutkit``); OpenCV and pyvista are imported only inside the functions that need them.
"""
from .rectangle import (
    BOX_FACES,
    RECTANGLE_SOLVERS,
    RectangleSolution,
    box_attitude,
    euler_zyx,
    euler_zyx_to_matrix,
    frame_rotation,
    label_symmetries,
    order_corners,
    rectangle_attitude,
    rectangle_corners,
    resolve_labelling,
    solve_rectangle,
    zhai_depth_ratios,
)
from .stream import AttitudeStream, RotationAlignment, align_rotation_streams, attitude_stream, track_corners

__all__ = [
    "AttitudeStream",
    "RotationAlignment",
    "align_rotation_streams",
    "attitude_stream",
    "track_corners",
    "BOX_FACES",
    "RECTANGLE_SOLVERS",
    "RectangleSolution",
    "box_attitude",
    "euler_zyx",
    "euler_zyx_to_matrix",
    "frame_rotation",
    "label_symmetries",
    "order_corners",
    "rectangle_attitude",
    "rectangle_corners",
    "resolve_labelling",
    "solve_rectangle",
    "zhai_depth_ratios",
]
