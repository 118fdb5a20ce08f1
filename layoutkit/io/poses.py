"""The pose table (CSV): THE reader and writer of layoutkit's pose files.

Every pose file layoutkit writes or reads — ``layoutkit solve --out``, the live/replay
``poses.csv``, the simulator's ``TRUTH.csv``, ``fake-fpga --motion`` and envelope trajectories —
is this one table. Foreign reference streams (motion capture, camera attitude: quaternion or
matrix columns, position only, ``.npy``) are read here too (:func:`read_reference`). Columns, in this order::

    t, station, status, rx, ry, rz, tx, ty, tz, residual_rms[, extra, ...]

- ``t`` : s.
- ``station`` : the station index as text (``0``, ``1``, ...) or ``joint`` for a pose solved
  from several stations at once (:data:`JOINT`, -1 in memory).
- ``status`` : int, 0 = ok; other values are the codes of the one status table,
  :mod:`layoutkit.status` (PnP and the live pipeline share it, so a code means the same in
  every pose file).
- ``rx, ry, rz`` : rotation vector, **radians**; ``tx, ty, tz`` : translation, **metres**. The pose
  maps body points into the frame of the file (station or world): ``p = R(r) p_body + t``.
- ``residual_rms`` : rad, RMS sweep-angle residual of the fit (NaN when not applicable).
- extras : any other named numeric columns (``n_lit``, ``adop``, ...), kept by name.

Reading is lenient in what it needs and strict in what it accepts: only ``t`` and the six pose
columns are required (a hand-written trajectory ``t,rx,ry,rz,tx,ty,tz`` is a pose table with
``station`` 0, ``status`` 0, ``residual_rms`` NaN). A column may carry its unit in the name —
``rx_deg`` / ``rx_rad``, ``tx_mm`` / ``tx_cm`` / ``tx_m`` / ``tx_in`` — and is converted to SI
on reading. An unknown unit suffix (``rx_grad``) is an error naming the column. The factor-57
bug: rotation columns without a unit are radians, and a canonical rotation vector has a norm of
at most pi, so a row whose untagged ``rx, ry, rz`` norm exceeds pi (a degree file fed to the
radians reader) is rejected with a message naming the file, line and columns. (A degree file
whose rotations all stay below pi degrees cannot be told from radians; name the columns
``rx_deg`` to be explicit.) Every error is a ``ValueError`` naming the file.

Writing is atomic (:func:`layoutkit.io.atomic.atomic_write`); :class:`PoseWriter` streams chunks
of a long run into one file that appears complete when the writer closes. Reading streams too
(:func:`iter_poses`), so memory stays bounded for any length.

Why one module of ~610 lines: the pose table and the foreign reference streams share the column
rules (unit tags, the degrees check) — one reader of every pose file.
"""
from __future__ import annotations

import csv
import io as _io
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..units import DEG, LENGTH_UNITS
from .atomic import atomic_write

__all__ = [
    "POSE_COLUMNS",
    "JOINT",
    "PoseTable",
    "PoseWriter",
    "write_poses",
    "read_poses",
    "iter_poses",
    "read_pose_header",
    "rotvec_columns",
    "check_rotvec_radians",
    "format_poses",
    "ReferenceTable",
    "read_reference",
]

#: The fixed leading columns of every pose table, in file order.
POSE_COLUMNS = ("t", "station", "status", "rx", "ry", "rz", "tx", "ty", "tz", "residual_rms")
#: In-memory station index of a pose solved from all stations jointly (``joint`` in the file).
JOINT = -1

_ROT = ("rx", "ry", "rz")
_POS = ("tx", "ty", "tz")
_ANGLE_UNITS = {"rad": 1.0, "deg": DEG}
_REQUIRED = ("t",) + _ROT + _POS
# rotation-vector norms above pi (plus rounding) are not canonical: a degree file read as radians
_PI_TOL = math.pi * (1.0 + 1e-9) + 1e-9


@dataclass(frozen=True)
class PoseTable:
    """Poses of ``N`` rows (arrays over rows), SI units.

    t : (N,) s; station : (N,) int (:data:`JOINT` = -1 for joint poses); status : (N,) int
    (0 = ok); rotvec : (N, 3) rad; translation : (N, 3) m; residual_rms : (N,) rad (NaN = n/a);
    extras : ``{name: (N,) float}`` other named columns, in file order. NaN pose entries mark
    rows without a pose (a failed solve).
    """

    t: np.ndarray
    rotvec: np.ndarray
    translation: np.ndarray
    station: np.ndarray | None = None
    status: np.ndarray | None = None
    residual_rms: np.ndarray | None = None
    extras: dict = field(default_factory=dict)

    def __post_init__(self):
        t = np.asarray(self.t, dtype=float).reshape(-1)
        n = t.shape[0]
        rv = np.asarray(self.rotvec, dtype=float).reshape(n, 3)
        tr = np.asarray(self.translation, dtype=float).reshape(n, 3)
        st = np.zeros(n, np.int64) if self.station is None else np.broadcast_to(
            np.asarray(self.station, dtype=np.int64), (n,)).copy()
        ss = np.zeros(n, np.int64) if self.status is None else np.broadcast_to(
            np.asarray(self.status, dtype=np.int64), (n,)).copy()
        rr = np.full(n, np.nan) if self.residual_rms is None else np.broadcast_to(
            np.asarray(self.residual_rms, dtype=float), (n,)).copy()
        ex = {}
        for name, v in dict(self.extras).items():
            name = str(name)
            if name in POSE_COLUMNS or not name or "," in name:
                raise ValueError(f"PoseTable.extras: bad column name {name!r}")
            ex[name] = np.broadcast_to(np.asarray(v, dtype=float), (n,)).copy()
        for k, v in (("t", t), ("rotvec", rv), ("translation", tr), ("station", st), ("status", ss),
                     ("residual_rms", rr), ("extras", ex)):
            object.__setattr__(self, k, v)

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @property
    def ok(self) -> np.ndarray:
        """(N,) bool, rows with status 0 and a finite pose."""
        return (self.status == 0) & np.all(np.isfinite(self.rotvec), -1) & np.all(np.isfinite(self.translation), -1)

    @property
    def columns(self) -> tuple[str, ...]:
        """The file header of this table."""
        return POSE_COLUMNS + tuple(self.extras)

    def rotation(self) -> np.ndarray:
        """(N, 3, 3) rotation matrices of the rotation vectors (NaN rows stay NaN)."""
        from ..geometry import rotvec_to_matrix

        return rotvec_to_matrix(self.rotvec)

    def take(self, index) -> "PoseTable":
        """Rows ``index`` (bool mask or integer indices) as a new table."""
        return PoseTable(self.t[index], self.rotvec[index], self.translation[index], self.station[index],
                         self.status[index], self.residual_rms[index],
                         {k: v[index] for k, v in self.extras.items()})

    @classmethod
    def concatenate(cls, tables) -> "PoseTable":
        """Row-wise concatenation of tables with the same extra columns."""
        tables = list(tables)
        if not tables:
            return cls(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)))
        names = tuple(tables[0].extras)
        for tb in tables[1:]:
            if tuple(tb.extras) != names:
                raise ValueError(f"PoseTable.concatenate: extra columns differ ({names} vs {tuple(tb.extras)})")
        cat = np.concatenate
        return cls(cat([tb.t for tb in tables]), cat([tb.rotvec for tb in tables]),
                   cat([tb.translation for tb in tables]), cat([tb.station for tb in tables]),
                   cat([tb.status for tb in tables]), cat([tb.residual_rms for tb in tables]),
                   {k: cat([tb.extras[k] for tb in tables]) for k in names})


# ------------------------------------------------------------------------------------- writing

def _format_rows(table: PoseTable) -> str:
    """CSV text of the rows of ``table`` (no header)."""
    n = len(table)
    if n == 0:
        return ""
    station = np.where(table.station == JOINT, "joint", table.station.astype(str))
    cols = [np.char.mod("%.9f", table.t), station, table.status.astype(str)]
    cols += [np.char.mod("%.12g", table.rotvec[:, k]) for k in range(3)]
    cols += [np.char.mod("%.12g", table.translation[:, k]) for k in range(3)]
    cols.append(np.char.mod("%.6g", table.residual_rms))
    cols += [np.char.mod("%.10g", v) for v in table.extras.values()]
    rows = cols[0].astype(object)
    for c in cols[1:]:
        rows = rows + "," + c.astype(object)
    return "\n".join(rows.tolist()) + "\n"


class PoseWriter:
    """Streams :class:`PoseTable` chunks into one pose CSV, atomically.

    ``PoseWriter(path, extras=("n_lit", ...))``; ``write(table)`` appends rows (each chunk must
    carry exactly ``extras``); ``close()`` renames the finished file into place (on an exception
    inside ``with PoseWriter(...)`` the target is left untouched). The header is the fixed
    :data:`POSE_COLUMNS` followed by ``extras``.
    """

    def __init__(self, path, extras=()):
        self.path = Path(path)
        self.extras = tuple(str(e) for e in extras)
        for name in self.extras:
            if name in POSE_COLUMNS or not name or "," in name:
                raise ValueError(f"{self.path}: bad extra column name {name!r}")
        self._cm = atomic_write(self.path, "w", newline="")
        self._fh = self._cm.__enter__()
        self._fh.write(",".join(POSE_COLUMNS + self.extras) + "\n")
        self.rows = 0
        self.closed = False

    def write(self, table: PoseTable) -> None:
        if tuple(table.extras) != self.extras:
            raise ValueError(f"{self.path}: chunk has extra columns {tuple(table.extras)}, "
                             f"the file was opened with {self.extras}")
        self._fh.write(_format_rows(table))
        self.rows += len(table)

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self._cm.__exit__(None, None, None)

    def abort(self, exc: BaseException | None = None) -> None:
        """Drop the temporary file; the target stays as it was."""
        if not self.closed:
            self.closed = True
            err = exc or RuntimeError("pose table aborted")
            try:
                self._cm.__exit__(type(err), err, None)
            except BaseException as raised:
                if raised is not err:
                    raise

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc is None:
            self.close()
        else:
            self.abort(exc)
        return False


def write_poses(path, table: PoseTable) -> Path:
    """Write ``table`` to ``path`` (atomically); returns the path."""
    with PoseWriter(path, tuple(table.extras)) as w:
        w.write(table)
    return Path(path)


# ------------------------------------------------------------------------------------- reading

@dataclass(frozen=True)
class _Header:
    path: str
    names: tuple            # as in the file
    index: dict             # canonical name → column index (t, station, status, rx..tz, residual_rms)
    scale: dict             # canonical name → factor to SI
    tagged: bool            # rotation columns carry a unit
    extras: tuple           # (name, index) of the other columns


def _split_unit(name: str):
    base, sep, unit = name.rpartition("_")
    return (base, unit) if sep else (name, None)


def read_pose_header(path, header_line: str, *, default_length_unit: str = "m") -> _Header:
    """Parse a pose-table header: which column holds what, and in which unit.

    default_length_unit : unit of untagged ``tx, ty, tz`` ("m" for every layoutkit file; a foreign
    motion-capture export in mm may say so here).
    """
    names = tuple(h.strip() for h in next(csv.reader([header_line])))
    index, scale, extras = {}, {}, []
    tagged = False
    if default_length_unit not in LENGTH_UNITS:
        raise ValueError(f"{path}: length unit: expected one of {', '.join(LENGTH_UNITS)}, "
                         f"got {default_length_unit!r}")
    for i, raw in enumerate(names):
        name = raw.lower()
        base, unit = _split_unit(name)
        if name in POSE_COLUMNS:
            canon, factor = name, (LENGTH_UNITS[default_length_unit] if name in _POS else 1.0)
        elif base in _ROT and unit is not None:
            if unit not in _ANGLE_UNITS:
                raise ValueError(f"{path}: column {raw!r}: unknown angle unit {unit!r} "
                                 f"(expected {base}, {base}_rad or {base}_deg)")
            canon, factor, tagged = base, _ANGLE_UNITS[unit], True
        elif base in _POS and unit is not None:
            if unit not in LENGTH_UNITS:
                raise ValueError(f"{path}: column {raw!r}: unknown length unit {unit!r} "
                                 f"(expected one of {', '.join(base + '_' + u for u in LENGTH_UNITS)})")
            canon, factor = base, LENGTH_UNITS[unit]
        elif base == "residual_rms" and unit is not None:
            if unit not in ("rad", "arcsec"):
                raise ValueError(f"{path}: column {raw!r}: unknown unit {unit!r} (expected rad)")
            from ..units import ARCSEC

            canon, factor = base, (1.0 if unit == "rad" else ARCSEC)
        else:
            if not raw:
                raise ValueError(f"{path}: column {i + 1} has an empty name")
            extras.append((raw, i))
            continue
        if canon in index:
            raise ValueError(f"{path}: column {canon!r} appears twice (as {names[index[canon]]!r} and {raw!r})")
        index[canon], scale[canon] = i, factor
    missing = [c for c in _REQUIRED if c not in index]
    if missing:
        raise ValueError(f"{path}: not a pose table: missing column(s) {', '.join(missing)} "
                         f"(expected {','.join(POSE_COLUMNS)}; rotation vector rad, or rx_deg,ry_deg,rz_deg; "
                         f"got {','.join(names) or '(empty header)'})")
    rot_units = {_split_unit(names[index[c]].lower())[1] for c in _ROT}
    if len(rot_units) > 1:
        raise ValueError(f"{path}: rotation columns {', '.join(names[index[c]] for c in _ROT)} mix units")
    return _Header(str(path), names, index, scale, tagged, tuple(extras))


def _rows_to_table(h: _Header, rows: list, first_line: int) -> PoseTable:
    n = len(rows)
    width = len(h.names)
    lens = np.fromiter((len(r) for r in rows), np.int64, n)
    if np.any(lens != width):
        k = int(np.flatnonzero(lens != width)[0])
        raise ValueError(f"{h.path}: line {first_line + k}: expected {width} values, got {lens[k]}")
    cells = np.char.strip(np.array(rows, dtype=str).reshape(n, width))
    st_col = h.index.get("station")
    station = None
    if st_col is not None:
        sc = cells[:, st_col]
        joint = np.char.lower(sc) == "joint"
        cells[:, st_col] = np.where(joint, "-1", sc)
    cells = np.where(cells == "", "nan", cells)  # empty cell = no value
    try:
        num = cells.astype(float)
    except ValueError:
        num = None
    if num is None:  # find the offending cell for the message
        for r in range(n):
            for c in range(width):
                try:
                    float(cells[r, c])
                except ValueError:
                    what = "expected an index or 'joint'" if c == st_col else "not a number"
                    raise ValueError(f"{h.path}: line {first_line + r}: column {h.names[c]}: {what} "
                                     f"({rows[r][c]!r})") from None
    if st_col is not None:
        s = num[:, st_col]
        bad = ~((s == JOINT) | ((s >= 0) & (s == np.round(s))))
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise ValueError(f"{h.path}: line {first_line + k}: column station: expected an index or 'joint', "
                             f"got {rows[k][st_col]!r}")
        station = s.astype(np.int64)
    col = lambda name: num[:, h.index[name]] * h.scale[name]  # noqa: E731
    t = col("t")
    if not np.all(np.isfinite(t)):
        bad = int(np.flatnonzero(~np.isfinite(t))[0])
        raise ValueError(f"{h.path}: line {first_line + bad}: column t: missing or non-finite time")
    rv = np.stack([col(c) for c in _ROT], -1)
    tr = np.stack([col(c) for c in _POS], -1)
    fin = np.all(np.isfinite(tr), 1)
    if fin.any():  # a lighthouse's volume is a room: km-sized positions are millimetres read as metres
        from .._validate import check_range

        check_range(float(np.max(np.linalg.norm(tr[fin], axis=1))),
                    f"{h.path}: columns {', '.join(h.names[h.index[c]] for c in _POS)} "
                    "(name them tx_mm, ty_mm, tz_mm if they are millimetres)")
    if not h.tagged:
        check_rotvec_radians(h.path, rv, [h.names[h.index[c]] for c in _ROT], first_line)
    status = np.zeros(n, np.int64)
    if "status" in h.index:
        s = num[:, h.index["status"]]
        bad = ~np.isfinite(s) | (s != np.round(s))
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise ValueError(f"{h.path}: line {first_line + k}: column status: expected an integer")
        status = s.astype(np.int64)
    res = col("residual_rms") if "residual_rms" in h.index else np.full(n, np.nan)
    extras = {name: num[:, i] for name, i in h.extras}
    return PoseTable(t, rv, tr, station, status, res, extras)


def rotvec_columns(path, names):
    """Locate a rotation vector in a CSV header: ``(indices (3,), factor to rad, tagged)`` or None.

    Accepts ``rx,ry,rz`` (radians), ``rx_rad,...`` or ``rx_deg,...`` (any case); an unknown unit
    suffix is a ``ValueError`` naming the column. Shared with the reference-stream reader.
    """
    low = [n.strip().lower() for n in names]
    found = []
    for base in _ROT:
        hits = [(i, _split_unit(n)[1] if n != base else None) for i, n in enumerate(low)
                if n == base or n.startswith(base + "_")]
        if not hits:
            return None
        i, unit = hits[0]
        if unit is not None and unit not in _ANGLE_UNITS:
            raise ValueError(f"{path}: column {names[i].strip()!r}: unknown angle unit {unit!r} "
                             f"(expected {base}, {base}_rad or {base}_deg)")
        found.append((i, unit))
    units = {u for _, u in found}
    if len(units) > 1:
        raise ValueError(f"{path}: rotation columns {', '.join(names[i].strip() for i, _ in found)} mix units")
    unit = units.pop()
    return [i for i, _ in found], (1.0 if unit is None else _ANGLE_UNITS[unit]), unit is not None


def check_rotvec_radians(path, rotvec, columns, first_line: int = 2, line_numbers=None) -> None:
    """Reject untagged rotation-vector columns that hold degrees (a row with norm > pi).

    rotvec : (N, 3) as read; columns : their names (for the message); line numbers are
    ``first_line + row`` unless ``line_numbers (N,)`` is given. NaN rows pass.
    """
    norm = np.linalg.norm(np.asarray(rotvec, float), axis=-1)
    big = np.flatnonzero(norm > _PI_TOL)
    if big.size:
        k = int(big[0])
        line = int(line_numbers[k]) if line_numbers is not None else first_line + k
        raise ValueError(
            f"{path}: line {line}: columns {','.join(columns)}: rotation vector norm {norm[k]:.4g} > pi — "
            f"pose tables hold the rotation vector in radians; this looks like degrees. "
            f"Convert to radians, or name the columns rx_deg,ry_deg,rz_deg")


def iter_poses(path, *, chunk_rows: int = 65536, default_length_unit: str = "m"):
    """Stream a pose table in chunks of at most ``chunk_rows`` rows: yields :class:`PoseTable`.

    Blank lines and lines starting with ``#`` are skipped. ``ValueError`` naming the file (and
    line and column) for a missing file, a non-pose header, unknown units or a degree file.
    """
    path = Path(path)
    try:
        fh = open(path, newline="")
    except FileNotFoundError:
        raise ValueError(f"{path}: no such pose table") from None
    except IsADirectoryError:
        raise ValueError(f"{path}: is a folder, not a pose table") from None
    with fh:
        lineno = 0
        header = None
        try:
            for line in fh:
                lineno += 1
                if line.strip() and not line.lstrip().startswith("#"):
                    header = read_pose_header(path, line, default_length_unit=default_length_unit)
                    break
        except UnicodeDecodeError:
            raise ValueError(f"{path}: not a text file (a pose table is CSV text)") from None
        if header is None:
            raise ValueError(f"{path}: empty pose table (no header)")
        rows, first = [], None
        try:
            for line in fh:
                lineno += 1
                if not line.strip() or line.lstrip().startswith("#"):
                    continue
                if first is None:
                    first = lineno
                rows.append(line.rstrip("\r\n").split(","))
                if len(rows) >= chunk_rows:
                    yield _rows_to_table(header, rows, first)
                    rows, first = [], None
        except UnicodeDecodeError:
            raise ValueError(f"{path}: not a text file") from None
        if rows:
            yield _rows_to_table(header, rows, first)


def read_poses(path, *, default_length_unit: str = "m", min_rows: int = 0) -> PoseTable:
    """Read a whole pose table (see the module docstring for the columns and checks).

    min_rows : fewer rows is a ``ValueError`` naming the file.
    """
    chunks = list(iter_poses(path, default_length_unit=default_length_unit))
    table = PoseTable.concatenate(chunks)
    if len(table) < min_rows:
        raise ValueError(f"{path}: pose table has {len(table)} row(s), need at least {min_rows}")
    return table


def format_poses(table: PoseTable) -> str:
    """The CSV text of ``table`` (header and rows), for callers that write to a stream."""
    buf = _io.StringIO()
    buf.write(",".join(table.columns) + "\n")
    buf.write(_format_rows(table))
    return buf.getvalue()


# ------------------------------------------------------------------- foreign reference streams

@dataclass(frozen=True)
class ReferenceTable:
    """A reference pose stream as read (motion capture, a camera attitude stream, TRUTH.csv).

    t : (N,) s, sorted (any clock origin); rotvec : (N, 3) rad or None (position only);
    translation : (N, 3) m or None (attitude only); dropped : rows left out for a non-finite time
    or value; dropped_lines : their line numbers in the file (CSV; empty for .npy rows, which
    have none); path : the file.
    """

    t: np.ndarray
    rotvec: np.ndarray | None
    translation: np.ndarray | None
    dropped: int = 0
    path: str = ""
    dropped_lines: tuple = ()


_REF_POS = (("x", "y", "z"), ("tx", "ty", "tz"))
_REF_QUAT = ("qx", "qy", "qz", "qw")
_REF_MATRIX = tuple(f"r{i}{j}" for i in (1, 2, 3) for j in (1, 2, 3))


def read_reference(path, units: str = "m") -> ReferenceTable:
    """Read a reference stream: THE reader of pose files that are not ours (and of ours).

    CSV with a header: ``t`` (s, any clock origin); attitude as ``rx,ry,rz`` (rotation vector,
    rad; ``rx_deg,...`` for degrees, the rules of this module), ``qx,qy,qz,qw`` (quaternion, scalar
    last) or ``r11..r33`` (row-major matrix), optional; position as ``x,y,z`` or ``tx,ty,tz`` in
    ``units`` ("m", "cm", "mm", "in"), optional; at least one of the two. A layoutkit pose table
    (TRUTH.csv, ``poses.csv``) is one such file (read by :func:`read_poses`, ``tx_mm`` tags
    honoured). Or ``.npy``: an ``(N, 4)`` array ``t, x, y, z`` or ``(N, 7)`` ``t, rx, ry, rz, x, y, z``.
    Rows with a non-finite time or value (attitude, position) are dropped and counted; at least 2
    rows must remain. Every error is a ``ValueError`` naming the file (and line and column).
    """
    from ..geometry import matrix_to_rotvec, nearest_rotation
    from ..rotations import quaternion_to_matrix

    if units not in LENGTH_UNITS:
        raise ValueError(f"units: expected one of {sorted(LENGTH_UNITS)}, got {units!r}")
    path = Path(path)
    scale = LENGTH_UNITS[units]
    if not path.is_file():
        raise ValueError(f"{path}: no such reference file")
    if path.suffix == ".npy":
        try:
            a = np.asarray(np.load(path, allow_pickle=False), float)
        except (ValueError, OSError):
            raise ValueError(f"{path}: not a readable .npy array") from None
        if a.ndim != 2 or a.shape[1] not in (4, 7):
            raise ValueError(f"{path}: expected an (N, 4) array t,x,y,z or (N, 7) t,rx,ry,rz,x,y,z, got {a.shape}")
        t, rv, pos, lines, check = a[:, 0], (a[:, 1:4] if a.shape[1] == 7 else None), a[:, -3:] * scale, None, None
    else:
        try:
            with open(path, newline="") as fh:
                first = fh.readline()
        except UnicodeDecodeError:
            raise ValueError(f"{path}: not a text (CSV) file") from None
        raw = next(csv.reader([first]), [])
        head = [h.strip().lower() for h in raw]
        col = {h: i for i, h in enumerate(head)}
        if "t" not in col:
            raise ValueError(f"{path}: no 't' column (header {head})")
        rot = rotvec_columns(path, raw)
        if rot is not None and (all(c in col for c in _POS) or any(h.startswith("tx_") for h in head)):
            try:
                read_pose_header(path, first, default_length_unit=units)
                is_table = True
            except ValueError:
                is_table = False
            if is_table:  # a pose table: its own reader
                tb = read_poses(path, default_length_unit=units)
                keep = np.all(np.isfinite(tb.rotvec), -1) & np.all(np.isfinite(tb.translation), -1)
                return _reference(path, tb.t[keep], tb.rotvec[keep], tb.translation[keep], int(np.sum(~keep)))
        quat = [col[c] for c in _REF_QUAT] if all(c in col for c in _REF_QUAT) else None
        mat = [col[c] for c in _REF_MATRIX] if all(c in col for c in _REF_MATRIX) else None
        pos_cols = next(([col[c] for c in names] for names in _REF_POS if all(c in col for c in names)), None)
        if rot is None and quat is None and mat is None and pos_cols is None:
            raise ValueError(f"{path}: expected attitude columns rx,ry,rz or qx,qy,qz,qw or r11..r33 and/or "
                             f"position columns x,y,z or tx,ty,tz, got header {head}")
        data, lines = _numeric_rows(path, raw)
        t = data[:, col["t"]]
        pos = None if pos_cols is None else data[:, pos_cols] * scale
        rv, check = None, None
        if rot is not None:
            rv = data[:, rot[0]] * rot[1]
            check = None if rot[2] else [raw[i].strip() for i in rot[0]]
        elif quat is not None or mat is not None:
            A = data[:, quat] if quat is not None else data[:, mat]
            ok = np.all(np.isfinite(A), 1) & (np.linalg.norm(A, axis=1) > 0)
            rv = np.full((len(t), 3), np.nan)
            if ok.any():
                R = quaternion_to_matrix(A[ok]) if quat is not None else nearest_rotation(A[ok].reshape(-1, 3, 3))
                rv[ok] = matrix_to_rotvec(R)
    keep = np.isfinite(t)
    for x in (rv, pos):
        if x is not None:
            keep &= np.all(np.isfinite(x), 1)
    if check is not None:
        check_rotvec_radians(path, rv[keep], check, line_numbers=lines[keep])
    if keep.sum() < 2:
        raise ValueError(f"{path}: fewer than 2 rows with a finite time and values")
    return _reference(path, t[keep], None if rv is None else rv[keep], None if pos is None else pos[keep],
                      int(np.sum(~keep)), () if lines is None else tuple(int(x) for x in lines[~keep]))


def _reference(path, t, rv, pos, dropped, dropped_lines=()) -> ReferenceTable:
    from .._validate import check_range

    order = np.argsort(t, kind="stable")
    if pos is not None and len(pos):  # a mocap volume is a room: km-sized positions are millimetres
        check_range(float(np.max(np.linalg.norm(pos, axis=1))), f"{path}: positions")
    return ReferenceTable(t[order], None if rv is None else rv[order], None if pos is None else pos[order],
                          dropped, str(path), dropped_lines)


def _numeric_rows(path, header):
    """The rows of a headed numeric CSV as ``(data (N, C) float, line numbers (N,))``; an empty
    cell is NaN, blank lines are skipped; a row of another width or a cell that is not a number is
    a ValueError naming the line and column."""
    names = [h.strip() for h in header]
    rows, lines = [], []
    with open(path, newline="") as fh:
        next(fh, None)
        for k, line in enumerate(fh, start=2):
            if line.strip():
                rows.append(line.rstrip("\r\n").split(","))
                lines.append(k)
    lines = np.asarray(lines, np.int64)
    if not rows:
        return np.zeros((0, len(names))), lines
    lens = np.fromiter((len(r) for r in rows), np.int64, len(rows))
    if np.any(lens != len(names)):
        k = int(np.flatnonzero(lens != len(names))[0])
        raise ValueError(f"{path}: line {lines[k]}: {lens[k]} fields, the header has {len(names)}")
    cells = np.char.strip(np.array(rows, dtype=str))
    cells = np.where(cells == "", "nan", cells)
    try:
        return cells.astype(float), lines
    except ValueError:
        for r, c in np.ndindex(cells.shape):
            try:
                float(cells[r, c])
            except ValueError:
                raise ValueError(f"{path}: line {lines[r]}, column {names[c]!r}: {rows[r][c].strip()[:30]!r} "
                                 "is not a number") from None
        raise
