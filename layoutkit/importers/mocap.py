"""Motion-capture references: ``t`` plus attitude and position, or position only.

CSV with a header: ``t`` (s, any clock origin), attitude as ``rx,ry,rz`` (rotation vector, rad),
``qx,qy,qz,qw`` (quaternion, scalar last) or ``r11..r33``, and position ``x,y,z`` or
``tx,ty,tz`` (in ``units``); the attitude is optional (position-only references, ``t,x,y,z``).
Or ``.npy``: an ``(N, 4)`` array ``t, x, y, z`` or ``(N, 7)`` ``t, rx, ry, rz, x, y, z``.
Rows with a non-finite time or position are dropped (counted). ``ValueError`` naming the file
and column otherwise.
"""
from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..units import LENGTH_UNITS

__all__ = ["Reference", "read_reference"]

_POS = (("x", "y", "z"), ("tx", "ty", "tz"))
_QUAT = ("qx", "qy", "qz", "qw")
_MAT = tuple(f"r{i}{j}" for i in (1, 2, 3) for j in (1, 2, 3))


@dataclass(frozen=True)
class Reference:
    """t (N,) s; rotvec (N, 3) rad or None (position only); position (N, 3) m; dropped rows."""

    t: np.ndarray
    rotvec: np.ndarray | None
    position: np.ndarray
    dropped: int = 0


def read_reference(path, units: str = "m") -> Reference:
    from scipy.spatial.transform import Rotation

    path = Path(path)
    if units not in LENGTH_UNITS:
        raise ValueError(f"units: expected one of {sorted(LENGTH_UNITS)}, got {units!r}")
    scale = LENGTH_UNITS[units]
    if not path.exists():
        raise ValueError(f"{path}: no such reference file")
    if path.suffix == ".npy":
        try:
            a = np.load(path, allow_pickle=False)
        except (ValueError, OSError):
            raise ValueError(f"{path}: not a readable .npy array") from None
        a = np.asarray(a, float)
        if a.ndim != 2 or a.shape[1] not in (4, 7):
            raise ValueError(f"{path}: expected an (N, 4) array t,x,y,z or (N, 7) t,rx,ry,rz,x,y,z, got {a.shape}")
        t, rv, pos = a[:, 0], (a[:, 1:4] if a.shape[1] == 7 else None), a[:, -3:] * scale
    else:
        try:
            with open(path, newline="") as fh:
                rows = list(csv.reader(fh))
        except UnicodeDecodeError:
            raise ValueError(f"{path}: not a text (CSV) file") from None
        if not rows:
            raise ValueError(f"{path}: empty file")
        head = [h.strip().lower() for h in rows[0]]
        col = {h: k for k, h in enumerate(head)}
        if "t" not in col:
            raise ValueError(f"{path}: no 't' column (header {head})")
        pos_cols = next((c for c in _POS if all(x in col for x in c)), None)
        if pos_cols is None:
            raise ValueError(f"{path}: no position columns x,y,z or tx,ty,tz (header {head})")
        data = []
        for k, r in enumerate(rows[1:], start=2):
            if not r or not any(x.strip() for x in r):
                continue
            if len(r) != len(head):
                raise ValueError(f"{path}: line {k}: {len(r)} fields, the header has {len(head)}")
            vals = []
            for j, x in enumerate(r):
                x = x.strip()
                try:
                    vals.append(float(x) if x else np.nan)
                except ValueError:
                    raise ValueError(f"{path}: line {k}, column {head[j]!r}: {x[:30]!r} is not a number") from None
            data.append(vals)
        d = np.asarray(data, float).reshape(-1, len(head))
        t = d[:, col["t"]]
        pos = d[:, [col[c] for c in pos_cols]] * scale
        rv = None
        if all(c in col for c in ("rx", "ry", "rz")):
            rv = d[:, [col["rx"], col["ry"], col["rz"]]]
            if np.nanmax(np.linalg.norm(rv, axis=1), initial=0.0) > np.pi * (1 + 1e-9):
                raise ValueError(f"{path}: columns rx, ry, rz: a rotation vector longer than pi rad "
                                 "(degrees? rotation vectors are in radians)")
        elif all(c in col for c in _QUAT):
            q = d[:, [col[c] for c in _QUAT]]
            ok = np.all(np.isfinite(q), 1) & (np.linalg.norm(q, axis=1) > 0)
            rv = np.full((len(t), 3), np.nan)
            rv[ok] = Rotation.from_quat(q[ok]).as_rotvec()
        elif all(c in col for c in _MAT):
            from ..geometry import matrix_to_rotvec, nearest_rotation

            M = d[:, [col[c] for c in _MAT]].reshape(-1, 3, 3)
            ok = np.all(np.isfinite(M), (1, 2))
            rv = np.full((len(t), 3), np.nan)
            rv[ok] = matrix_to_rotvec(nearest_rotation(M[ok]))
    keep = np.isfinite(t) & np.all(np.isfinite(pos), 1)
    if rv is not None:
        keep &= np.all(np.isfinite(rv), 1)
    if keep.sum() < 2:
        raise ValueError(f"{path}: fewer than 2 rows with a finite time and position")
    order = np.argsort(t[keep], kind="stable")
    return Reference(t[keep][order], None if rv is None else rv[keep][order], pos[keep][order],
                     int(np.sum(~keep)))
