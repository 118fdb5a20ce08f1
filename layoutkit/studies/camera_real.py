"""The camera cross-check on real photographs (issue 28): ``studies/camera_real``.

``main(out_dir, data_dir, quick)`` runs, on OpenCV's 13 sample photos of a hand-held 9 x 6
chessboard (25 mm squares, a lens with k1 ≈ -0.27; ``tests/data/camera`` = ``shared/data/camera``):

1. **calibration** (:func:`layoutkit.workflows.camera.calibrate_images`, i.e. ``camera calibrate``)
   against ``left_intrinsics.yml`` (OpenCV's own calibration of the same photos);
2. **4 extreme corners vs all corners**: per photo the attitude from the board's 4 extreme inner
   corners (an 8 x 5-square rectangle, aspect 1.600) by Zhai's size-free solver, the homography
   method and IPPE with the aspect known, each with and without undistortion, against the
   attitude from all 54 corners (``cv2.solvePnP``, iterative, with the lens) — the reference;
3. **predicted vs observed disagreement**: the disagreement's linear prediction (corners shared
   by both estimates, so the Jacobian of the *difference* is used: the 4-corner solver's J on its
   corners minus the reference's Gauss-Newton J on all 54, times the photo's corner noise, the
   reference's residual RMS with 2n - 6 dof; plus the calibration covariance through the
   difference of the two estimates' parameter Jacobians);
4. **the face detector** (:func:`layoutkit.camera.face_detect.detect_face`) on every photo: the
   white paper sheet of the board is a bright rectangle against a cluttered office. Its true
   corners are not printed, but it is one physical rectangle in the board plane: its four edges
   (board coordinates) are fitted to the detected corners of the other photos (through each
   photo's all-corner pose) and predict this photo's corners — the leave-one-out corner error
   (px). A detection whose error exceeds 10 px is counted as a wrong outline (and left out of
   the fits). The Zhai attitude from the detected paper corners is compared with the reference;
5. **synthetic camera with distortion**: a 0.2 x 0.125 m face rendered through the same lens
   (blur 0.7 px, 4 grey levels of noise, 4x supersampled), ``draws`` noise draws of the same
   render, detector → solver: Monte-Carlo attitude scatter / predicted σ (detector covariance
   through the lens), for the face detector and for ``detect_quadrilateral`` with the lens.

Writes ``results.json``, ``table.md``, ``attitude_errors.png``, ``predicted_vs_observed.png``,
``detections.png``, ``calibration_residuals.png`` and ``camera.yml`` into ``out_dir``.
Long (~450 lines) because the study's figures and tables are part of it.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from ..io.atomic import atomic_write_text
from ..io.figures import save_figure
from ..io.jsonfile import to_jsonable

__all__ = ["main", "all_corner_reference", "paper_rectangle_loo", "synthetic_monte_carlo", "DEFAULT_DATA"]

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "tests" / "data" / "camera"
INNER = (9, 6)
SQUARE_M = 0.025


def _dphi_per_rvec(rvec, h=1e-6):
    """G (3, 3): small-rotation change per rotation-vector change at ``rvec`` (left perturbation)."""
    from ..geometry import matrix_to_rotvec, rotvec_to_matrix

    R0 = rotvec_to_matrix(rvec)
    G = np.zeros((3, 3))
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        G[:, k] = (matrix_to_rotvec(rotvec_to_matrix(rvec + e) @ R0.T)
                   - matrix_to_rotvec(rotvec_to_matrix(rvec - e) @ R0.T)) / (2 * h)
    return G


def all_corner_reference(view, K, D):
    """The reference: ``cv2.solvePnP`` (iterative, with the lens) on every corner of a view.

    Returns dict: R_cv (3, 3), rvec, tvec, sigma_px (per-coordinate residual RMS, 2n - 6 dof),
    J_px (3, 2n) small rotation (OpenCV camera frame) per observed corner coordinate (Gauss-Newton),
    and ``solve(K, D)`` to re-solve with another camera (for parameter Jacobians).
    """
    import cv2

    obj, img = view.object_points, view.image_points

    def solve(Ki, Di, guess=None):
        if guess is None:
            ok, rv, tv = cv2.solvePnP(obj, img, Ki, Di, flags=cv2.SOLVEPNP_ITERATIVE)
        else:
            ok, rv, tv = cv2.solvePnP(obj, img, Ki, Di, guess[0].copy(), guess[1].copy(), True,
                                      cv2.SOLVEPNP_ITERATIVE)
        return rv.ravel(), tv.ravel()

    rv, tv = solve(K, D)
    rv, tv = solve(K, D, (rv, tv))
    proj, J = cv2.projectPoints(obj, rv, tv, K, D)
    e = (img - proj.reshape(-1, 2)).ravel()
    n = e.size
    sigma = float(np.sqrt(e @ e / max(n - 6, 1)))
    Jp = J[:, :6]
    pose_per_obs = np.linalg.solve(Jp.T @ Jp, Jp.T)  # (6, 2n)
    G = _dphi_per_rvec(rv)
    return {"R_cv": cv2.Rodrigues(rv)[0], "rvec": rv, "tvec": tv, "sigma_px": sigma, "J_px": G @ pose_per_obs[:3],
            "solve": lambda Ki, Di: solve(Ki, Di, (rv, tv)), "G": G}


def _reference_param_jacobian(ref, K, D, p, rel=1e-4):
    """(3, p) small rotation (OpenCV camera frame) of the reference per camera parameter."""
    from ..camera.lens import model_from_parameters, model_parameter_vector
    from ..geometry import matrix_to_rotvec, rotvec_to_matrix

    v0 = model_parameter_vector(K, D)
    R0 = ref["R_cv"]
    J = np.zeros((3, p))
    for i in range(p):
        h = rel * max(abs(v0[i]), 1.0) if i < 4 else rel
        out = []
        for s in (1.0, -1.0):
            v = v0.copy()
            v[i] += s * h
            Ki, Di = model_from_parameters(v, len(D), skew=K[0, 1])
            rv, _ = ref["solve"](Ki, Di)
            out.append(matrix_to_rotvec(rotvec_to_matrix(rv) @ R0.T))
        J[:, i] = (out[0] - out[1]) / (2 * h)
    return J


def _extreme_corner_study(views, K, D, C_theta):
    """Item 2 + 3 per photo: errors of every method (deg) and the predicted disagreement of Zhai."""
    from ..camera.calibration import BOARD_FROM_FACE, board_rectangle
    from ..camera.conventions import PAPER_FROM_CV
    from ..camera.face import attitude_jacobian_camera, attitude_jacobian_pixels, face_attitude
    from ..geometry import attitude_error

    methods = (("zhai", None), ("homography", None), ("ippe", (INNER[0] - 1) / (INNER[1] - 1)))
    rows = []
    idx = [(INNER[1] - 1) * INNER[0], INNER[1] * INNER[0] - 1, 0, INNER[0] - 1]
    p = C_theta.shape[0]
    M = PAPER_FROM_CV
    for v in views:
        ref = all_corner_reference(v, K, D)
        R_ref = M @ ref["R_cv"] @ BOARD_FROM_FACE
        c, _ = board_rectangle(v, INNER)
        row = {"image": v.name, "grid_sigma_px": ref["sigma_px"]}
        for name, ar in methods:
            for und in (True, False):
                fa = face_attitude(c, K, D if und else None, method=name, aspect_ratio=ar, ordered=True,
                                   predict=False)
                key = f"{name}_{'undistorted' if und else 'raw'}_deg"
                row[key] = float(np.degrees(attitude_error(fa.rotation, R_ref))) if fa.success else None
                if name == "zhai" and und:
                    row["tilt_deg"] = fa.tilt_deg
                    R_z = fa.rotation
        # predicted disagreement of the undistorted Zhai solve (item 3)
        Jz = attitude_jacobian_pixels(c, K, D, R_z, "zhai")  # (3, 8) paper frame, observed px
        Jd = -(M @ ref["J_px"])  # (3, 2n)
        for k, i in enumerate(idx):
            Jd[:, 2 * i:2 * i + 2] += Jz[:, 2 * k:2 * k + 2]
        var_corners = ref["sigma_px"] ** 2 * float(np.trace(Jd @ Jd.T))
        Jt = attitude_jacobian_camera(c, K, D, R_z, "zhai", None, range(p))[:, :p] - M @ _reference_param_jacobian(
            ref, K, D, p)
        var_cam = float(np.trace(Jt @ C_theta @ Jt.T))
        var_zhai_alone = ref["sigma_px"] ** 2 * float(np.trace(Jz @ Jz.T))
        row.update(predicted_deg=float(np.degrees(np.sqrt(var_corners + var_cam))),
                   predicted_corners_deg=float(np.degrees(np.sqrt(var_corners))),
                   predicted_camera_deg=float(np.degrees(np.sqrt(var_cam))),
                   predicted_zhai_alone_deg=float(np.degrees(np.sqrt(var_zhai_alone))))
        row["_R_ref"] = R_ref
        row["_ref"] = ref
        rows.append(row)
    return rows


def paper_rectangle_loo(detections, refs, K, D, bad_px: float = 10.0):
    """Leave-one-out corner error (px) of the detected paper corners (module docstring, item 4).

    detections : list of (4, 2) or None; refs : list of all_corner_reference dicts. Returns
    (errors (n, 4) NaN where not detected, wrong (n,) bool, edges (x0, x1, y0, y1) m of the fit
    on every correct detection)."""
    import cv2
    from scipy.optimize import least_squares

    n = len(detections)

    def residual(p, idx):
        x0, x1, y0, y1 = p
        P = np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]])
        out = []
        for k in idx:
            pr = cv2.projectPoints(P, refs[k]["rvec"], refs[k]["tvec"], K, D)[0].reshape(-1, 2)
            j = [int(np.argmin(np.linalg.norm(pr - q, axis=1))) for q in detections[k]]
            out.append((detections[k] - pr[j]).ravel())
        return np.concatenate(out)

    found = [k for k in range(n) if detections[k] is not None]
    wrong = np.zeros(n, bool)
    p0 = np.array([-0.02, (INNER[0] - 1) * SQUARE_M + 0.02, -0.02, (INNER[1] - 1) * SQUARE_M + 0.02])
    err = np.full((n, 4), np.nan)
    for _ in range(3):  # fit, flag wrong outlines, refit without them
        good = [k for k in found if not wrong[k]]
        for k in found:
            others = [j for j in good if j != k]
            fit = least_squares(residual, p0, args=(others,), loss="soft_l1", f_scale=2.0)
            err[k] = np.linalg.norm(residual(fit.x, [k]).reshape(-1, 2), axis=1)
        new = np.zeros(n, bool)
        new[found] = np.nanmax(err[found], axis=1) > bad_px
        if np.array_equal(new, wrong):
            break
        wrong = new
    good = [k for k in found if not wrong[k]]
    edges = least_squares(residual, p0, args=(good,)).x if good else np.full(4, np.nan)
    return err, wrong, edges


def synthetic_monte_carlo(draws: int = 200, seed: int = 0) -> dict:
    """Item 5: detector → solver scatter vs predicted σ on renders through the sample lens."""
    import trimesh

    from ..camera.corners import detect_quadrilateral
    from ..camera.face import face_attitude
    from ..camera.face_detect import detect_face
    from ..camera.synthetic import PinholeCamera, SyntheticCamera
    from ..geometry import attitude_error, matrix_to_rotvec, rotvec_to_matrix

    D = (-0.266, -0.0386, 0.00178, -0.00028, 0.238)
    cam = PinholeCamera(640, 480, 535.9, 342.3, 235.6, D)
    face = np.array([[-0.1, -0.0625, 0.0], [0.1, -0.0625, 0.0], [0.1, 0.0625, 0.0], [-0.1, 0.0625, 0.0]])
    mesh = trimesh.Trimesh(vertices=face, faces=[[0, 1, 2], [0, 2, 3]])
    R = rotvec_to_matrix(np.radians([25, -20, 10]))
    t = np.array([0.12, 0.08, 0.55])
    rng = np.random.default_rng(seed)
    with SyntheticCamera(mesh, cam, lighting="flat", supersample=4, face_colors=np.full((2, 3), 200, np.uint8),
                         background=(40, 40, 40)) as sc:
        clean = sc.render(R, t, blur_sigma_px=0.7).astype(np.float32)
    K, Dv = cam.K, np.array(D)
    truth_px = cam.project(R, t, face)
    out = {"pose_rotvec_deg": [25, -20, 10], "translation_m": t.tolist(), "draws": draws, "noise_grey": 4.0,
           "blur_px": 0.7}
    for name in ("detect_face", "detect_quadrilateral"):
        Rs, pred, cerr = [], [], []
        ref = None
        for _ in range(draws):
            img = np.clip(np.rint(clean + rng.normal(0, 4.0, clean.shape)), 0, 255).astype(np.uint8)
            if name == "detect_face":
                d = detect_face(img, K, Dv, polarity="bright")
                c, cov = d.corners_px, d.corner_cov_px
            else:
                d = detect_quadrilateral(img, camera_matrix=K, distortion=Dv, edge_correlation="measured")
                c, cov = d.corners_px, d.corner_cov_px
            if not d.success:
                continue
            fa = face_attitude(c, K, Dv, corner_cov_px=cov, reference=ref)
            ref = fa.rotation if ref is None else ref
            Rs.append(fa.rotation)
            pred.append(fa.sigma_deg)
            cerr.append(np.min(np.linalg.norm(c[:, None] - truth_px[None], axis=-1), axis=1))
        Rs = np.array(Rs)
        mean = Rs.mean(0)
        from ..geometry import nearest_rotation

        Rm = nearest_rotation(mean)
        e = matrix_to_rotvec(Rs @ Rm.T)
        obs = float(np.degrees(np.sqrt(np.mean(np.sum(e ** 2, 1)))))
        p_rms = float(np.sqrt(np.mean(np.square(pred))))
        bias = float(np.degrees(attitude_error(Rm, _truth_paper(R))))
        out[name] = {"found": len(Rs), "scatter_deg": obs, "predicted_deg": p_rms, "ratio": obs / p_rms,
                     "corner_error_px_median": float(np.median(cerr)), "corner_error_px_max": float(np.max(cerr)),
                     "mean_attitude_error_deg": bias}
    return out


def _truth_paper(R_cv):
    from ..camera.conventions import PAPER_FROM_CV

    B = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]])
    return PAPER_FROM_CV @ R_cv @ B


def main(out_dir, data_dir=None, quick: bool = False) -> dict:
    """Run the study (module docstring); returns the results dict (also ``results.json``)."""
    import cv2

    from ..camera.calibration import find_pattern
    from ..camera.face import face_attitude
    from ..camera.face_detect import detect_face
    from ..geometry import attitude_error
    from ..io.camera import read_camera_model
    from ..workflows.camera import calibrate_images

    t0 = time.time()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    data = Path(data_dir) if data_dir is not None else DEFAULT_DATA
    photos = sorted(data.glob("left*.jpg"))
    if not photos:
        raise ValueError(f"{data}: no left*.jpg photos")
    published = read_camera_model(data / "left_intrinsics.yml")
    # 1. calibration
    cal = calibrate_images(photos, out / "camera.yml", inner=INNER, square_mm=SQUARE_M * 1e3,
                           figure=out / "calibration_residuals.png")
    cam = read_camera_model(out / "camera.yml")
    K, D = cam.matrix, cam.distortion
    rel = {n: float(cam.matrix[i, j] / published.matrix[i, j] - 1)
           for n, (i, j) in zip(("fx", "fy", "cx", "cy"), ((0, 0), (1, 1), (0, 2), (1, 2)))}
    try:
        data_name = str(data.resolve().relative_to(DEFAULT_DATA.parents[2]))
    except ValueError:
        data_name = str(data)
    res = {"data": data_name, "photos": [p.name for p in photos],
           "calibration": {"rms_px": cal["rms_px"], "status": cal["status"], "outliers": cal["outliers"],
                           "relative_to_left_intrinsics": rel, "camera_matrix": K, "distortion": D,
                           "published_distortion": published.distortion, "std_dev": cal["std_dev"]}}
    # 2-3. extreme corners vs all corners
    imgs = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in photos]
    views = [find_pattern(g, "chessboard", INNER, SQUARE_M, name=p.name) for g, p in zip(imgs, photos)]
    rows = _extreme_corner_study(views, K, D, cam.covariance)
    summ = {}
    for key in [k for k in rows[0] if k.endswith("_deg") and not k.startswith(("tilt", "predicted"))]:
        e = np.array([r[key] for r in rows], float)
        summ[key] = {"median": float(np.nanmedian(e)), "max": float(np.nanmax(e)), "rms": float(np.sqrt(np.nanmean(e ** 2)))}
    e_z = np.array([r["zhai_undistorted_deg"] for r in rows])
    p_z = np.array([r["predicted_deg"] for r in rows])
    res["extreme_corners"] = {
        "per_photo": [{k: v for k, v in r.items() if not k.startswith("_")} for r in rows], "summary": summ,
        "predicted_vs_observed": {"observed_rms_deg": float(np.sqrt(np.mean(e_z ** 2))),
                                  "predicted_rms_deg": float(np.sqrt(np.mean(p_z ** 2))),
                                  "ratio": float(np.sqrt(np.mean(e_z ** 2)) / np.sqrt(np.mean(p_z ** 2))),
                                  "within_2_sigma": int(np.sum(e_z <= 2 * p_z)), "photos": len(rows)}}
    # 4. face detector
    dets, msgs = [], []
    for g in imgs:
        d = detect_face(g, K, D)
        dets.append(d if d.success else None)
        msgs.append(d.message)
    refs = [r["_ref"] for r in rows]
    err, wrong, edges = paper_rectangle_loo([None if d is None else d.corners_px for d in dets], refs, K, D)
    good = [k for k in range(len(dets)) if dets[k] is not None and not wrong[k]]
    att = []
    for k in good:
        fa = face_attitude(dets[k].corners_px, K, D, corner_cov_px=dets[k].corner_cov_px, camera_cov=cam.covariance)
        from ..camera.rectangle import resolve_labelling

        R = resolve_labelling(fa.rotation, rows[k]["_R_ref"], 4)
        att.append({"image": photos[k].name, "error_deg": float(np.degrees(attitude_error(R, rows[k]["_R_ref"]))),
                    "predicted_sigma_deg": fa.sigma_deg, "aspect_ratio": fa.aspect_ratio})
    ce = err[good].ravel()
    res["face_detector"] = {
        "found": int(sum(d is not None for d in dets)), "correct_outline": len(good), "photos": len(dets),
        "wrong_outline": [photos[k].name for k in range(len(dets)) if wrong[k]],
        "not_found": [photos[k].name for k in range(len(dets)) if dets[k] is None],
        "messages": {photos[k].name: msgs[k] for k in range(len(dets))},
        "corner_error_px": {"median": float(np.median(ce)) if ce.size else None,
                            "p95": float(np.percentile(ce, 95)) if ce.size else None,
                            "max": float(np.max(ce)) if ce.size else None},
        "per_photo_corner_error_px": {photos[k].name: err[k] for k in range(len(dets))},
        "paper_edges_board_m": edges, "paper_size_mm": [float((edges[1] - edges[0]) * 1e3),
                                                         float((edges[3] - edges[2]) * 1e3)],
        "zhai_from_paper_corners": att,
        "zhai_from_paper_corners_median_deg": float(np.median([a["error_deg"] for a in att])) if att else None,
        "zhai_from_paper_corners_rms_deg": float(np.sqrt(np.mean([a["error_deg"] ** 2 for a in att]))) if att else None,
        "zhai_from_paper_corners_predicted_rms_deg":
            float(np.sqrt(np.mean([a["predicted_sigma_deg"] ** 2 for a in att]))) if att else None}
    # 5. synthetic camera with distortion
    res["synthetic_monte_carlo"] = synthetic_monte_carlo(60 if quick else 200)
    res["quick"] = quick
    res["elapsed_s"] = time.time() - t0
    _figures(out, rows, res, imgs, dets, wrong, K, D)
    atomic_write_text(out / "results.json", json.dumps(to_jsonable(res), indent=2) + "\n")
    atomic_write_text(out / "table.md", _table(res))
    return res


def _figures(out, rows, res, imgs, dets, wrong, K, D):
    import cv2
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..camera.lens import distort_pixels, undistort_pixels
    from ..io.atomic import atomic_write_bytes

    names = [Path(r["image"]).stem for r in rows]
    x = np.arange(len(rows))
    fig, ax = plt.subplots(figsize=(10, 4.2))
    for off, key, lab in ((-0.3, "zhai_undistorted_deg", "Zhai, undistorted"), (-0.1, "ippe_undistorted_deg",
                                                                               "IPPE (aspect 1.6), undistorted"),
                          (0.1, "zhai_raw_deg", "Zhai, lens ignored"), (0.3, "ippe_raw_deg", "IPPE, lens ignored")):
        ax.bar(x + off, [r[key] for r in rows], width=0.2, label=lab)
    ax.plot(x - 0.3, [r["predicted_deg"] for r in rows], "k_", ms=14, mew=2, label="predicted 1-sigma (Zhai)")
    ax.set_xticks(x)
    ax.set_xticklabels(names, rotation=45, fontsize=8)
    ax.set_yscale("log")
    ax.set_xlabel("photo")
    ax.set_ylabel("attitude error vs all-corner solvePnP (deg)")
    ax.set_title("4 extreme chessboard corners vs all 54 corners, 13 real photos")
    ax.legend(fontsize=7, ncol=3)
    s = res["extreme_corners"]["summary"]
    save_figure(fig, out / "attitude_errors.png",
                caption=f"Zhai undistorted: median {s['zhai_undistorted_deg']['median']:.2f}, max "
                        f"{s['zhai_undistorted_deg']['max']:.2f} deg; lens ignored: median "
                        f"{s['zhai_raw_deg']['median']:.2f}, max {s['zhai_raw_deg']['max']:.2f} deg.")
    fig, ax = plt.subplots(figsize=(5.5, 5))
    p = np.array([r["predicted_deg"] for r in rows])
    e = np.array([r["zhai_undistorted_deg"] for r in rows])
    ax.plot(p, e, "o")
    for xi, yi, n in zip(p, e, names):
        ax.annotate(n, (xi, yi), fontsize=6)
    lim = max(p.max(), e.max()) * 1.1
    ax.plot([0, lim], [0, lim], "k-", lw=0.8, label="observed = predicted")
    ax.plot([0, lim], [0, 2 * lim], "k:", lw=0.8, label="2x")
    ax.set_xlabel("predicted 1-sigma disagreement (deg)")
    ax.set_ylabel("observed disagreement (deg)")
    ax.set_title("Zhai (4 corners) vs all corners: predicted vs observed")
    ax.legend(fontsize=8)
    pv = res["extreme_corners"]["predicted_vs_observed"]
    save_figure(fig, out / "predicted_vs_observed.png",
                caption=f"RMS observed {pv['observed_rms_deg']:.3f} deg vs predicted {pv['predicted_rms_deg']:.3f} deg "
                        f"(ratio {pv['ratio']:.2f}); {pv['within_2_sigma']}/{pv['photos']} within 2 sigma.")
    tiles = []
    for k, g in enumerate(imgs):
        vis = cv2.cvtColor(g, cv2.COLOR_GRAY2BGR)
        d = dets[k]
        if d is not None:
            ring = undistort_pixels(d.corners_px, K, D)
            s_ = np.linspace(0, 1, 40, endpoint=False)
            poly = np.concatenate([ring[i] + (ring[(i + 1) % 4] - ring[i]) * s_[:, None] for i in range(4)])
            col = (0, 0, 255) if wrong[k] else (0, 220, 0)
            cv2.polylines(vis, [np.round(distort_pixels(poly, K, D) * 8).astype(np.int32)], True, col, 2,
                          cv2.LINE_AA, shift=3)
        cv2.putText(vis, Path(res["photos"][k]).stem + ("" if d is not None else " not found")
                    + (" WRONG" if wrong[k] else ""), (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (0, 255, 255), 2)
        tiles.append(cv2.resize(vis, (320, 240), interpolation=cv2.INTER_AREA))
    while len(tiles) % 4:
        tiles.append(np.zeros_like(tiles[0]))
    mont = np.vstack([np.hstack(tiles[i:i + 4]) for i in range(0, len(tiles), 4)])
    ok, buf = cv2.imencode(".png", mont)
    atomic_write_bytes(out / "detections.png", buf.tobytes())


def _table(res) -> str:
    c = res["calibration"]
    s = res["extreme_corners"]["summary"]
    pv = res["extreme_corners"]["predicted_vs_observed"]
    fd = res["face_detector"]
    mc = res["synthetic_monte_carlo"]
    lines = ["# Camera cross-check on real photographs (issue 28)", "",
             f"Data: {len(res['photos'])} photos ({res['data']}); quick = {res['quick']}.", "",
             "## Calibration (`camera calibrate`) vs left_intrinsics.yml", "",
             "| quantity | value |", "|---|---|",
             f"| RMS reprojection error | {c['rms_px']:.3f} px |",
             "| fx, fy, cx, cy relative to left_intrinsics.yml | "
             + ", ".join(f"{k} {100 * v:+.3f} %" for k, v in c["relative_to_left_intrinsics"].items()) + " |",
             f"| outlier photos | {', '.join(c['outliers']) or 'none'} |", "",
             "## 4 extreme corners vs all-corner solvePnP (deg)", "",
             "| method | median | max | RMS |", "|---|---|---|---|"]
    for k, v in s.items():
        lines.append(f"| {k.replace('_deg', '')} | {v['median']:.3f} | {v['max']:.3f} | {v['rms']:.3f} |")
    lines += ["", f"Predicted vs observed (Zhai, undistorted): RMS observed {pv['observed_rms_deg']:.3f} deg, "
                  f"predicted {pv['predicted_rms_deg']:.3f} deg, ratio {pv['ratio']:.2f}; "
                  f"{pv['within_2_sigma']} of {pv['photos']} photos within 2 sigma.", "",
              "| photo | tilt (deg) | Zhai und. | Zhai raw | IPPE und. | predicted 1-sigma (corners, camera) |",
              "|---|---|---|---|---|---|"]
    for r in res["extreme_corners"]["per_photo"]:
        lines.append(f"| {r['image']} | {r['tilt_deg']:.1f} | {r['zhai_undistorted_deg']:.3f} | {r['zhai_raw_deg']:.3f} "
                     f"| {r['ippe_undistorted_deg']:.3f} | {r['predicted_deg']:.3f} ({r['predicted_corners_deg']:.3f}, "
                     f"{r['predicted_camera_deg']:.3f}) |")
    ce = fd["corner_error_px"]
    lines += ["", "## Face detector (paper sheet of the board)", "",
              f"Found {fd['found']} of {fd['photos']}, correct outline {fd['correct_outline']} "
              f"(wrong: {', '.join(fd['wrong_outline']) or 'none'}; not found: {', '.join(fd['not_found']) or 'none'}).",
              f"Leave-one-out corner error vs the chessboard-predicted paper corners: median {ce['median']:.2f} px, "
              f"p95 {ce['p95']:.2f} px, max {ce['max']:.2f} px; paper {fd['paper_size_mm'][0]:.1f} x "
              f"{fd['paper_size_mm'][1]:.1f} mm.",
              f"Zhai from the detected paper corners (aspect unknown) vs the reference: median "
              f"{fd['zhai_from_paper_corners_median_deg']:.3f} deg, RMS {fd['zhai_from_paper_corners_rms_deg']:.3f} deg; "
              f"predicted RMS {fd['zhai_from_paper_corners_predicted_rms_deg']:.3f} deg (the detector's line-fit "
              "covariance + the calibration: it does not see the sheet's own departures from a flat rectangle, "
              "which the leave-one-out corner error measures).", "",
              "## Synthetic camera with distortion (Monte-Carlo)", "",
              "| detector | draws found | scatter (deg) | predicted (deg) | ratio | corner error median / max (px) |",
              "|---|---|---|---|---|---|"]
    for name in ("detect_face", "detect_quadrilateral"):
        m = mc[name]
        lines.append(f"| {name} | {m['found']} / {mc['draws']} | {m['scatter_deg']:.4f} | {m['predicted_deg']:.4f} | "
                     f"{m['ratio']:.3f} | {m['corner_error_px_median']:.3f} / {m['corner_error_px_max']:.3f} |")
    return "\n".join(lines) + "\n"
