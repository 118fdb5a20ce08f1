"""Frame files: simulated sweep-angle frames written and read for ``layoutkit simulate`` /
``layoutkit solve``.

Format (documented in docs/frames.md): CSV with header
``t,th_x_<id>,th_y_<id>,...`` (rad, empty/NaN = not lit) and optional truth columns
``true_rx,true_ry,true_rz,true_tx,true_ty,true_tz`` (rotation vector rad, m); or ``.npz`` with
arrays ``t (F,)``, ``angles (F, n, 2)``, ``ids (n,)`` and optional ``truth_rotvec``, ``truth_translation``.
"""
from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..geometry import matrix_to_rotvec, rotvec_to_matrix
from ..layout import Layout

__all__ = ["Frames", "simulate_frames", "write_frames", "read_frames", "solve_frames", "solution_table",
           "simulate_frame_file", "solve_frame_file"]

GROSS_DEG = 1.0
_TRUTH = ["true_rx", "true_ry", "true_rz", "true_tx", "true_ty", "true_tz"]


@dataclass(frozen=True)
class Frames:
    """t (F,) s; angles (F, n, 2) rad (NaN = not lit); ids; optional truth rotation (F,3,3), translation (F,3)."""

    t: np.ndarray
    angles: np.ndarray
    ids: tuple
    truth_rotation: np.ndarray | None = None
    truth_translation: np.ndarray | None = None


def simulate_frames(layout: Layout, frames: int, *, seed: int, sigma: float, rho: float,
                    half_angle_deg: float = 60.0, min_lit: int = 4, rate_hz: float = 60.0,
                    quantize: bool = True) -> Frames:
    """Static random poses on the paper's area in front of the station, ≥ ``min_lit`` lit."""
    from ..simulate import poses_in_front, simulate_angles
    from ..visibility import facing_mask

    rng = np.random.default_rng(seed)
    Rs, ts, vs = [], [], []
    n_have = 0
    while n_have < frames:
        R, t = poses_in_front(max(64, 2 * frames), rng)
        v = facing_mask(layout.positions, layout.normals, R, t, half_angle_deg=half_angle_deg)
        k = v.sum(1) >= min_lit
        Rs.append(R[k]); ts.append(t[k]); vs.append(v[k])
        n_have += int(k.sum())
    R = np.concatenate(Rs)[:frames]
    t = np.concatenate(ts)[:frames]
    v = np.concatenate(vs)[:frames]
    ang = simulate_angles(layout.positions, R, t, sigma=sigma, rho=rho, rng=rng, quantize=quantize)
    ang[~v] = np.nan
    return Frames(np.arange(frames) / rate_hz, ang, layout.ids, R, t)


def write_frames(fr: Frames, path) -> None:
    """Write a frame table (.csv) or .npz atomically: ``path`` is complete or untouched."""
    from ..io.atomic import atomic_write

    path = Path(path)
    if path.suffix == ".npz":
        extra = {}
        if fr.truth_rotation is not None:
            extra = {"truth_rotvec": matrix_to_rotvec(fr.truth_rotation), "truth_translation": fr.truth_translation}
        with atomic_write(path, "wb") as fh:
            np.savez_compressed(fh, t=fr.t, angles=fr.angles, ids=np.asarray(fr.ids), **extra)
        return
    header = ["t"] + [f"th_{ax}_{i}" for i in fr.ids for ax in ("x", "y")]
    rows = np.column_stack([fr.t, fr.angles.reshape(len(fr.t), -1)])
    if fr.truth_rotation is not None:
        header += _TRUTH
        rows = np.column_stack([rows, matrix_to_rotvec(fr.truth_rotation), fr.truth_translation])
    with atomic_write(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        for r in rows:
            w.writerow(["" if not np.isfinite(x) else repr(float(x)) for x in r])


def read_frames(path, layout: Layout) -> Frames:
    """Read a frame file; the sensor ids must match the layout's (ValueError otherwise)."""
    path = Path(path)
    if not path.exists():
        raise ValueError(f"{path}: no such frame file")
    if path.suffix == ".npz":
        try:
            d = np.load(path, allow_pickle=False)
            need = [k for k in ("t", "angles", "ids") if k not in d.files]
            if need:
                raise KeyError(", ".join(need))
            ids = tuple(str(i) for i in d["ids"])
            ang = np.asarray(d["angles"], float)
            R = rotvec_to_matrix(d["truth_rotvec"]) if "truth_rotvec" in d else None
            T = np.asarray(d["truth_translation"]) if "truth_translation" in d else None
            t = np.asarray(d["t"], float)
        except KeyError as exc:
            raise ValueError(f"{path}: frame .npz lacks {exc.args[0]}; expected arrays t, angles, ids") from None
        except (OSError, EOFError, ValueError):  # not an .npz (zip of plain arrays) at all
            raise ValueError(f"{path}: not a readable .npz frame file") from None
    else:
        try:
            with open(path, newline="") as fh:
                rd = csv.reader(fh)
                header = next(rd, None)
                if not header or header[0] != "t":
                    raise ValueError(f"{path}: expected a CSV header starting with 't'")
                rows = []
                for r in rd:
                    if not r:
                        continue
                    if len(r) != len(header):
                        raise ValueError(f"{path}: line {rd.line_num}: {len(r)} fields, the header has {len(header)}")
                    try:
                        rows.append([float(x) if x.strip() else np.nan for x in r])
                    except ValueError:
                        bad = next(x for x in r if x.strip() and not _is_number(x))
                        raise ValueError(f"{path}: line {rd.line_num}: {bad[:40]!r} is not a number") from None
        except UnicodeDecodeError:
            raise ValueError(f"{path}: not a text (CSV) frame file") from None
        data = np.asarray(rows, float).reshape(-1, len(header))
        cols = {h: k for k, h in enumerate(header)}
        ids = tuple(h[5:] for h in header if h.startswith("th_x_"))
        ang = np.stack([np.column_stack([data[:, cols[f"th_x_{i}"]], data[:, cols[f"th_y_{i}"]]]) for i in ids], 1)
        t = data[:, 0]
        R = T = None
        if all(h in cols for h in _TRUTH):
            tr = data[:, [cols[h] for h in _TRUTH]]
            R, T = rotvec_to_matrix(tr[:, :3]), tr[:, 3:]
    if len(t) == 0:
        raise ValueError(f"{path}: no frames")
    if not np.all(np.isfinite(t)):
        raise ValueError(f"{path}: frame {int(np.argmin(np.isfinite(t)))}: time t is empty, NaN or infinite")
    if np.isinf(ang).any():
        raise ValueError(f"{path}: frame {int(np.isinf(ang).any((1, 2)).argmax())}: infinite angle "
                         "(use an empty cell or NaN for a sensor that is not lit)")
    for name, tr in (("truth rotation", R), ("truth translation", T)):
        if tr is not None and not np.all(np.isfinite(tr)):
            bad = int(np.argmin(np.isfinite(tr.reshape(len(tr), -1)).all(1)))
            raise ValueError(f"{path}: frame {bad}: {name} is empty, NaN or infinite")
    missing = [i for i in ids if i not in layout.ids]
    if missing:
        raise ValueError(f"{path}: sensor ids {missing[:5]} are not in the layout")
    order = [ids.index(i) if i in ids else -1 for i in layout.ids]
    full = np.full((ang.shape[0], layout.n, 2), np.nan)
    for j, k in enumerate(order):
        if k >= 0:
            full[:, j] = ang[:, k]
    return Frames(t, full, layout.ids, R, T)


def _is_number(x: str) -> bool:
    try:
        float(x)
    except ValueError:
        return False
    return True


def solution_table(res: dict):
    """The per-frame results of :func:`solve_frames` as a pose table (:mod:`layoutkit.io.poses`)."""
    from ..io.poses import PoseTable

    return PoseTable(res["t"], res["rotvec"], res["translation"], status=res["status"],
                     residual_rms=res["residual_rms"])


def solve_frames(fr: Frames, layout: Layout, *, sigma: float | None = None, rho: float = 0.0,
                 method: str = "lm") -> dict:
    """Solve every frame; summary with statuses, and errors against truth when the file has it.

    method : a key of :data:`layoutkit.pnp.PNP_SOLVERS`.
    """
    from ..dop import pose_dop, pose_errors, rms
    from ..pnp import solve_pnp

    from ..pnp import STATUS_AMBIGUOUS, STATUS_NAMES

    vis = np.all(np.isfinite(fr.angles), -1)
    sol = solve_pnp(layout.positions, fr.angles, vis, method=method,
                    **({} if sigma is None else {"sigma": sigma, "rho": rho}))
    out = {"frames": int(len(fr.t)), "solved": int(np.sum(sol.success)),
           "status_counts": {int(k): int(v) for k, v in zip(*np.unique(sol.status, return_counts=True))},
           "t": fr.t, "rotvec": matrix_to_rotvec(sol.rotation), "translation": sol.translation,
           "success": sol.success, "status": sol.status, "residual_rms": sol.residual_rms}
    if fr.truth_rotation is not None:
        ok = np.asarray(sol.success)
        e_r, e_t = pose_errors(sol.rotation[ok], sol.translation[ok], fr.truth_rotation[ok], fr.truth_translation[ok])
        # gross: > 1 deg off — with 4 coplanar lit sensors the planar two-fold ambiguity is
        # undecidable under noise for some poses (docs/pnp.md), so report them apart
        gross = np.degrees(e_r) > GROSS_DEG
        good = ~gross
        out.update(rms_rot_deg=float(np.degrees(rms(e_r))), rms_trans_m=float(rms(e_t)),
                   max_rot_deg=float(np.degrees(e_r.max())) if ok.any() else None,
                   gross_failures=int(gross.sum()),
                   gross_failures_by_status={STATUS_NAMES[0]: int(gross.sum())},
                   rms_rot_deg_without_gross=float(np.degrees(rms(e_r[good]))),
                   rms_trans_m_without_gross=float(rms(e_t[good])))
        amb = np.flatnonzero(np.asarray(sol.status) == STATUS_AMBIGUOUS)
        if amb.size:  # neither candidate is reported as the pose; say how often the truth is among them
            e1, _ = pose_errors(sol.rotation[amb], sol.translation[amb], fr.truth_rotation[amb], fr.truth_translation[amb])
            e2, _ = pose_errors(sol.alt_rotation[amb], sol.alt_translation[amb], fr.truth_rotation[amb],
                                fr.truth_translation[amb])
            out["gross_failures_by_status"]["ambiguous (best candidate)"] = int(np.sum(np.degrees(e1) > GROSS_DEG))
            out["ambiguous"] = {"frames": int(amb.size),
                                "truth_within_1deg_of_a_candidate": int(np.sum(np.degrees(np.minimum(e1, e2)) <= GROSS_DEG))}
        if sigma is not None:
            sel = np.flatnonzero(ok)[good]
            d = pose_dop(layout.positions, fr.truth_rotation[sel], fr.truth_translation[sel], rho=rho, visible=vis[sel])
            out.update(predicted_rms_rot_deg=float(np.sqrt(np.mean(d.adop**2)) * sigma),
                       predicted_rms_trans_m=float(np.sqrt(np.mean(d.pdop**2)) * sigma))
    return out


def simulate_frame_file(layout: Layout, frames: int, out, *, seed: int, sigma: float, rho: float,
                        quantize: bool = True) -> dict:
    """What ``layoutkit simulate`` does: :func:`simulate_frames`, written to ``out`` (.csv or .npz).

    Returns the summary ``{out, frames, mean_lit, min_lit}`` (lit sensors per frame).
    """
    fr = simulate_frames(layout, frames, seed=seed, sigma=sigma, rho=rho, quantize=quantize)
    write_frames(fr, out)
    lit = np.all(np.isfinite(fr.angles), -1).sum(1)
    return {"out": str(out), "frames": int(frames), "mean_lit": float(lit.mean()), "min_lit": int(lit.min())}


def solve_frame_file(frames_path, layout: Layout, *, out=None, sigma: float | None = None, rho: float = 0.0,
                     method: str = "lm", filter_settings: dict | None = None) -> dict:
    """What ``layoutkit solve`` does: read a frame file, solve every frame, write the pose table to ``out``
    (:mod:`layoutkit.io.poses`: t, station, status, rx, ry, rz, tx, ty, tz, residual_rms; rad, m).

    filter_settings : None, or keywords of :class:`layoutkit.filter.EkfConfig` (see
    :func:`layoutkit.workflows.filter.filter_config`): the frames also go through the tracking
    filter, ``out`` then holds the filtered poses and the summary a ``filter`` entry.
    Returns the JSON-ready summary of :func:`solve_frames` (without the per-frame arrays).
    ValueError (naming the file) for an unreadable frame file or filter settings.
    """
    fr = read_frames(frames_path, layout)
    res = solve_frames(fr, layout, sigma=sigma, rho=rho, method=method)
    fres = None
    if filter_settings is not None:
        from .filter import filter_config, filter_frames

        try:
            fres = filter_frames(fr, layout, filter_config(filter_settings, sigma, rho))
        except ValueError as exc:
            raise ValueError(f"{frames_path}: {exc}") from None
    if out:
        from ..io.poses import write_poses

        if fres is None:
            write_poses(out, solution_table(res))
        else:
            from .filter import filter_table

            write_poses(out, filter_table(fres))
    summary = {k: v for k, v in res.items()
               if k not in ("t", "rotvec", "translation", "success", "status", "residual_rms")}
    if fres is not None:
        summary["filter"] = {k: v for k, v in fres.items()
                             if k not in ("t", "rotvec", "translation", "status", "cov_rot_deg", "cov_pos_m")}
    return summary
