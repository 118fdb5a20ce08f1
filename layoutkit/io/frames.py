"""THE FRAME TABLE: sweep-angle frames, one reader and one writer (docs/frames.md).

CSV with a header ``t[,station],th_x_<id>,th_y_<id>,...[,true_rx,...,true_tz]``:

- ``t`` : seconds, finite;
- ``station`` (optional) : integer index of the base station that swept the frame
  (the ``station`` entries of a stations JSON); absent = one station, index 0;
- ``th_x_<id>``, ``th_y_<id>`` : the two sweep angles of sensor ``<id>`` in radians,
  ``theta_x = atan2(z, x)`` in the station frame (design §2); an EMPTY cell (or ``nan``) means
  that angle was not seen. Each axis is its own observation: a sensor seen on one axis only has
  one empty cell, not a dropped sensor;
- ``true_rx, true_ry, true_rz`` (rotation vector, rad), ``true_tx, true_ty, true_tz`` (m),
  optional, all six or none: the true pose (simulations) — the body pose in the frame of the row's
  station (``layoutkit simulate --stations``: world pose = ``R_s R``, ``R_s t + T_s``).

Or ``.npz`` with arrays ``t (F,)``, ``angles (F, n, 2)``, ``ids (n,)`` and optional
``station (F,)``, ``truth_rotvec (F, 3)``, ``truth_translation (F, 3)``.

The reader checks everything at the boundary and raises ``ValueError`` naming the file, the
column and the line (never ``KeyError``): a missing ``t``, a renamed or unknown column, an angle
column without its partner axis, a text cell, a line with the wrong number of fields. Values that
are well-formed numbers but physically wrong (inf, angles outside (0, pi), degrees) are kept: the
solver gives those frames a status (:mod:`layoutkit.pnp`), so one bad frame never stops a batch.
"""
from __future__ import annotations

import csv
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..geometry import matrix_to_rotvec, rotvec_to_matrix
from .atomic import atomic_write

__all__ = ["Frames", "TRUTH_COLUMNS", "read_frame_table", "write_frame_table", "frame_columns"]

TRUTH_COLUMNS = ("true_rx", "true_ry", "true_rz", "true_tx", "true_ty", "true_tz")
_ANGLE = re.compile(r"^th_([xy])_(.+)$")


@dataclass(frozen=True)
class Frames:
    """Sweep-angle frames.

    t : (F,) s; angles : (F, n, 2) rad, ``[theta_x, theta_y]``, NaN = that angle not seen;
    ids : n sensor ids (str); station : (F,) int station index or None (one station);
    truth_rotation (F, 3, 3), truth_translation (F, 3) m : optional true poses.
    """

    t: np.ndarray
    angles: np.ndarray
    ids: tuple
    truth_rotation: np.ndarray | None = None
    truth_translation: np.ndarray | None = None
    station: np.ndarray | None = None

    @property
    def n_frames(self) -> int:
        return int(len(self.t))

    @property
    def seen(self) -> np.ndarray:
        """(F, n, 2) bool, the angles present (not NaN)."""
        return ~np.isnan(self.angles)

    def stations(self) -> np.ndarray:
        """(F,) int station index (0 where the table has no station column)."""
        if self.station is None:
            return np.zeros(len(self.t), int)
        return np.asarray(self.station, int)


def frame_columns(ids, *, station: bool = True, truth: bool = False) -> list[str]:
    """The CSV header for sensor ``ids``."""
    cols = ["t"] + (["station"] if station else [])
    cols += [f"th_{ax}_{i}" for i in ids for ax in ("x", "y")]
    return cols + (list(TRUTH_COLUMNS) if truth else [])


def _fmt(x: float) -> str:
    return repr(float(x)) if np.isfinite(x) else ("" if np.isnan(x) else ("inf" if x > 0 else "-inf"))


def write_frame_table(fr: Frames, path) -> None:
    """Write ``fr`` to ``path`` (``.npz`` or CSV), atomically."""
    path = Path(path)
    truth = fr.truth_rotation is not None and fr.truth_translation is not None
    if path.suffix == ".npz":
        extra = {}
        if truth:
            extra.update(truth_rotvec=matrix_to_rotvec(fr.truth_rotation), truth_translation=fr.truth_translation)
        if fr.station is not None:
            extra["station"] = np.asarray(fr.station, int)
        with atomic_write(path, "wb") as fh:
            np.savez_compressed(fh, t=fr.t, angles=fr.angles, ids=np.asarray(fr.ids), **extra)
        return
    has_station = fr.station is not None
    header = frame_columns(fr.ids, station=has_station, truth=truth)
    F = len(fr.t)
    ang = np.asarray(fr.angles, float).reshape(F, -1)
    tru = np.column_stack([matrix_to_rotvec(fr.truth_rotation), fr.truth_translation]) if truth else None
    st = fr.stations()
    with atomic_write(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        for k in range(F):
            row = [repr(float(fr.t[k]))]
            if has_station:
                row.append(str(int(st[k])))
            row += [_fmt(x) for x in ang[k]]
            if truth:
                row += [_fmt(x) for x in tru[k]]
            w.writerow(row)


def _number(cell: str, path, line: int, col: str) -> float:
    s = cell.strip()
    if not s:
        return np.nan
    try:
        return float(s)
    except ValueError:
        raise ValueError(f"{path}: line {line}, column {col!r}: {s[:40]!r} is not a number") from None


def _parse_header(header: list[str], path) -> tuple[list[str], dict]:
    """Check the header; returns the sensor ids in column order and the column index map."""
    if not header:
        raise ValueError(f"{path}: empty file; expected a CSV header starting with column 't'")
    names = [h.strip() for h in header]
    if names[0] != "t":
        hint = " (renamed? the time column must be called 't', in seconds)" if names[0].lower() in (
            "time", "t_s", "timestamp", "time_s") else ""
        raise ValueError(f"{path}: first column is {names[0]!r}, expected 't'{hint}")
    seen = {}
    for k, h in enumerate(names):
        if h in seen:
            raise ValueError(f"{path}: column {h!r} appears twice (columns {seen[h] + 1} and {k + 1})")
        seen[h] = k
    ids, unknown = [], []
    for h in names[1:]:
        m = _ANGLE.match(h)
        if m:
            if m.group(1) == "x":
                ids.append(m.group(2))
        elif h != "station" and h not in TRUTH_COLUMNS:
            unknown.append(h)
    if unknown:
        raise ValueError(f"{path}: unknown column(s) {unknown[:5]}; a frame table has 't', 'station', "
                         "'th_x_<id>', 'th_y_<id>' (rad) and the truth columns " + ", ".join(TRUTH_COLUMNS))
    for h in names[1:]:
        m = _ANGLE.match(h)
        if m:
            other = f"th_{'y' if m.group(1) == 'x' else 'x'}_{m.group(2)}"
            if other not in seen:
                raise ValueError(f"{path}: column {other!r} is missing (column {h!r} is present; every sensor "
                                 "has both axes, empty cells where an angle was not seen)")
    if not ids:
        raise ValueError(f"{path}: no angle columns 'th_x_<id>', 'th_y_<id>' in the header")
    tr = [h for h in TRUTH_COLUMNS if h in seen]
    if tr and len(tr) != len(TRUTH_COLUMNS):
        miss = [h for h in TRUTH_COLUMNS if h not in seen]
        raise ValueError(f"{path}: truth column(s) {miss} missing (give all of {', '.join(TRUTH_COLUMNS)} or none)")
    return ids, seen


def _read_csv(path):
    try:
        with open(path, newline="") as fh:
            rd = csv.reader(fh)
            header = next(rd, None)
            ids, cols = _parse_header(header, path)
            names = [h.strip() for h in header]
            rows = []
            for r in rd:
                if not r or (len(r) == 1 and not r[0].strip()):
                    continue
                if len(r) != len(names):
                    raise ValueError(f"{path}: line {rd.line_num}: {len(r)} fields, the header has {len(names)}")
                rows.append([_number(x, path, rd.line_num, names[j]) for j, x in enumerate(r)])
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a text (CSV) frame file") from None
    except csv.Error as exc:
        raise ValueError(f"{path}: not a readable CSV frame file ({exc})") from None
    data = np.asarray(rows, float).reshape(-1, len(names))
    t = data[:, 0]
    ang = np.stack([np.column_stack([data[:, cols[f"th_x_{i}"]], data[:, cols[f"th_y_{i}"]]]) for i in ids], 1)
    station = None
    if "station" in cols:
        s = data[:, cols["station"]]
        bad = ~np.isfinite(s) | (s < 0) | (s != np.round(s))
        if bad.any():
            k = int(np.argmax(bad))
            raise ValueError(f"{path}: line {k + 2}, column 'station': {float(s[k])!r} is not a station index "
                             "(an integer >= 0)")
        station = s.astype(int)
    R = T = None
    if "true_rx" in cols:
        tr = data[:, [cols[h] for h in TRUTH_COLUMNS]]
        R, T = rotvec_to_matrix(tr[:, :3]), tr[:, 3:]
    return t, ang, tuple(ids), station, R, T


def _read_npz(path):
    try:
        d = np.load(path, allow_pickle=False)
        files = set(d.files)
    except (OSError, EOFError, ValueError):  # not an .npz (zip of plain arrays) at all
        raise ValueError(f"{path}: not a readable .npz frame file") from None
    need = [k for k in ("t", "angles", "ids") if k not in files]
    if need:
        raise ValueError(f"{path}: frame .npz lacks array(s) {', '.join(need)}; expected t, angles, ids")
    t = np.asarray(d["t"], float).reshape(-1)
    ang = np.asarray(d["angles"], float)
    ids = tuple(str(i) for i in np.asarray(d["ids"]).reshape(-1))
    if ang.ndim != 3 or ang.shape[1:] != (len(ids), 2) or ang.shape[0] != len(t):
        raise ValueError(f"{path}: array 'angles' has shape {ang.shape}, expected ({len(t)}, {len(ids)}, 2)")
    station = np.asarray(d["station"], int).reshape(-1) if "station" in files else None
    R = rotvec_to_matrix(d["truth_rotvec"]) if "truth_rotvec" in files else None
    T = np.asarray(d["truth_translation"], float) if "truth_translation" in files else None
    return t, ang, ids, station, R, T


def _check_radians(path, ang, ids) -> None:
    """Frame-table angles are radians in (0, pi) (LH1-equivalent sweep angles). A file whose finite
    angles are mostly outside that range holds degrees (or another unit): refused, naming the first
    such column and line. A few stray values stay per-frame ``invalid_angle`` statuses."""
    fin = np.isfinite(ang)
    if not fin.any():
        return
    out = fin & ((ang <= 0.0) | (ang >= np.pi))
    if out.sum() > 0.5 * fin.sum():
        f, k, a = (int(x[0]) for x in np.nonzero(out))
        raise ValueError(f"{path}: line {f + 2}, column th_{'xy'[a]}_{ids[k]}: {float(ang[f, k, a]):.6g} is outside "
                         f"(0, pi) rad, like {100 * out.sum() / fin.sum():.0f} % of the angles: frame tables hold "
                         "radians; these look like degrees")


def read_frame_table(path, layout_ids=None) -> Frames:
    """Read a frame table; ``ValueError`` naming file, column and line on malformed content.

    layout_ids : optional sensor ids of the layout; the table's ids must be among them and the
    angles are returned in the layout's order (columns absent from the file are all NaN).
    """
    path = Path(path)
    if not path.exists():
        raise ValueError(f"{path}: no such frame file")
    if path.is_dir():
        raise ValueError(f"{path}: is a folder, expected a frame file (.csv or .npz)")
    t, ang, ids, station, R, T = _read_npz(path) if path.suffix == ".npz" else _read_csv(path)
    if len(t) == 0:
        raise ValueError(f"{path}: no frames")
    if not np.all(np.isfinite(t)):
        k = int(np.argmin(np.isfinite(t)))
        raise ValueError(f"{path}: frame {k} (line {k + 2}), column 't': time is empty, NaN or infinite")
    for name, tr in (("truth rotation", R), ("truth translation", T)):
        if tr is not None and not np.all(np.isfinite(tr)):
            bad = int(np.argmin(np.isfinite(tr.reshape(len(tr), -1)).all(1)))
            raise ValueError(f"{path}: frame {bad} (line {bad + 2}): {name} is empty, NaN or infinite")
    if station is not None and len(station) != len(t):
        raise ValueError(f"{path}: 'station' has {len(station)} entries for {len(t)} frames")
    _check_radians(path, ang, ids)
    if layout_ids is not None:
        layout_ids = tuple(str(i) for i in layout_ids)
        missing = [i for i in ids if i not in layout_ids]
        if missing:
            raise ValueError(f"{path}: sensor id(s) {missing[:5]} (columns th_x_{missing[0]}, ...) are not in "
                             f"the layout (layout ids: {list(layout_ids)[:8]}{' ...' if len(layout_ids) > 8 else ''})")
        full = np.full((ang.shape[0], len(layout_ids), 2), np.nan)
        for k, i in enumerate(ids):
            full[:, layout_ids.index(i)] = ang[:, k]
        ang, ids = full, layout_ids
    return Frames(t, ang, tuple(ids), R, T, station)
