"""Station calibration models (layoutkit.lighthouse): each public reference formula, re-typed here
independently from its C source, must equal the one internal model mapped from that project's own
parameters to 1e-12 (proof by independent re-implementation); analytic Jacobians must equal central
finite differences (proof by finite differences)."""
import math

import numpy as np
import pytest

from layoutkit.lighthouse import (
    CALIBRATION_PARAMS, Calibration, SweepCalibration, StationCalibration, calibrate_lh1, calibrate_lh2,
    calibration_from_crazyflie, calibration_from_dict, calibration_from_libsurvive, distort, lh1_model,
    lh2_model, lh2_sweep_angles, lh2_to_lh1_angles, measure, measure_jacobian, sweep_angles, undistort,
)

N = 400


def _points(rng, n=N):
    """Points in the station frame (z = boresight), inside a 110° field, 0.5-4 m."""
    z = rng.uniform(0.5, 4.0, n)
    return np.column_stack([z * np.tan(rng.uniform(-0.95, 0.95, n)),
                            z * np.tan(rng.uniform(-0.95, 0.95, n)), z])


def _factory(rng):
    """Random factory-like values in a project's own convention: {name: [axis0, axis1]}."""
    return {"phase": rng.uniform(-0.06, 0.06, 2), "tilt": rng.uniform(-0.04, 0.04, 2),
            "curve": rng.uniform(-0.01, 0.01, 2), "gib_phase": rng.uniform(-np.pi, np.pi, 2),
            "gib_mag": rng.uniform(-0.03, 0.03, 2), "ogee_phase": rng.uniform(-np.pi, np.pi, 2),
            "ogee_mag": rng.uniform(-0.05, 0.05, 2)}


# ----------------------------------------------------------------------------- libsurvive
# Re-typed from cntools/libsurvive src/survive_reproject.c (survive_reproject_axis and the x/y
# wrappers): libsurvive's lighthouse frame has objects in front at -Z.
def _ls_axis(phase, tilt, curve, gibpha, gibmag, axis_value, other, Z, invert):
    ang = math.pi / 2 - (-1 if invert else 1) * math.atan2(axis_value, Z)
    mag = math.sqrt(axis_value * axis_value + Z * Z)
    ang -= phase
    ang -= math.asin(min(max(tilt * other / mag, -1.0), 1.0))
    ang -= math.cos(gibpha + ang) * gibmag
    ang += curve * math.atan2(other, Z) * math.atan2(other, Z)
    return ang


def _ls_lh1(cal, pt):
    c = lambda k: (cal["phase"][k], cal["tilt"][k], cal["curve"][k], cal["gib_phase"][k], cal["gib_mag"][k])  # noqa
    return (_ls_axis(*c(0), pt[0], pt[1], -pt[2], False) - math.pi / 2,
            _ls_axis(*c(1), pt[1], pt[0], -pt[2], True) - math.pi / 2)


# Re-typed from src/survive_reproject_gen2.c (calc_cal_series, survive_reproject_axis_gen2).
def _ls_series(s):
    f = [-8.0108022e-06, 0.0028679863, 5.3685255000000001e-06, 0.0076069798000000001, 0.0, 0.0]
    m, a = f[0], 0.0
    for i in range(1, 6):
        a = a * s + m
        m = m * s + f[i]
    return m, a


def _ls_axis_gen2(cal, k, X, Y, Z, axis):
    phase, tilt, curve = cal["phase"][k], cal["tilt"][k], cal["curve"][k]
    gibpha, gibmag = cal["gib_phase"][k], cal["gib_mag"][k]
    ogeephase, ogeemag = cal["ogee_phase"][k], cal["ogee_mag"][k]
    clip = lambda v: min(max(v, -1.0), 1.0)  # noqa: E731
    B = math.atan2(Z, X)
    Ydeg = tilt + (-1 if axis else 1) * math.pi / 6
    tanA = math.tan(Ydeg)
    normXZ = math.sqrt(X * X + Z * Z)
    asinArg = clip(tanA * Y / normXZ)
    sinYdeg, cosYdeg = math.sin(Ydeg), math.cos(Ydeg)
    sinPart = math.sin(B - math.asin(asinArg) + ogeephase) * ogeemag
    normXYZ = math.sqrt(X * X + Y * Y + Z * Z)
    asinOut = math.asin(clip(Y / normXYZ / cosYdeg))
    mod, acc = _ls_series(asinOut)
    BcalCurved = sinPart + curve
    asinArg2 = clip(asinArg + mod * BcalCurved / (cosYdeg - acc * BcalCurved * sinYdeg))
    asinOut2 = math.asin(asinArg2)
    sinOut2 = math.sin(B - asinOut2 + gibpha)
    return B - asinOut2 + sinOut2 * gibmag - phase - math.pi / 2


def _ls_lh2(cal, pt):
    return (_ls_axis_gen2(cal, 0, pt[0], pt[1], -pt[2], False),
            _ls_axis_gen2(cal, 1, pt[0], pt[1], -pt[2], True))


_LS_FRAME = np.diag([1.0, -1.0, -1.0])  # our station frame -> libsurvive's lighthouse frame


@pytest.mark.parametrize("kind", ["lh1", "lh2"])
def test_libsurvive_formula_equals_internal_model(rng, kind):
    """libsurvive's reprojection (own parameters, own frame and angle origin) == measure() mapped via
    calibration_from_libsurvive, to 1e-12 rad: LH1 theta = a + pi/2, LH2 alpha = -a."""
    for _ in range(5):
        cal = _factory(rng)
        p = _points(rng)
        ours = measure(p, calibration_from_libsurvive(cal, kind))
        ref = np.array([(_ls_lh1 if kind == "lh1" else _ls_lh2)(cal, _LS_FRAME @ q) for q in p])
        ref = ref + np.pi / 2 if kind == "lh1" else -ref
        np.testing.assert_allclose(ours, ref, rtol=0, atol=1e-12)
        # and the distortion is real (the test would notice a model that ignored the parameters)
        assert np.abs(ours - measure(p, kind=kind)).max() > 1e-3


def test_libsurvive_recording_keys_accepted(rng):
    """The recording's fcal* names map to the same model as the BaseStationCal names."""
    cal = _factory(rng)
    keyed = {"fcalphase": cal["phase"], "fcaltilt": cal["tilt"], "fcalcurve": cal["curve"],
             "fcalgibpha": cal["gib_phase"], "fcalgibmag": cal["gib_mag"],
             "fcalogeephase": cal["ogee_phase"], "fcalogeemag": cal["ogee_mag"]}
    a = calibration_from_dict(keyed, "lh2")
    np.testing.assert_array_equal(a.params, calibration_from_libsurvive(cal, "lh2").params)
    short = {"convention": "libsurvive", "phase": cal["phase"], "tilt": cal["tilt"], "curve": cal["curve"],
             "gibpha": cal["gib_phase"], "gibmag": cal["gib_mag"], "ogeephase": cal["ogee_phase"],
             "ogeemag": cal["ogee_mag"]}               # BaseStationCal field names (the importer's)
    np.testing.assert_array_equal(calibration_from_dict(short, "lh2").params, a.params)
    b = calibration_from_dict(a.to_dict())
    np.testing.assert_array_equal(b.params, a.params)
    assert (b.kind, b.gib_argument) == ("lh2", "corrected")
    with pytest.raises(ValueError, match="calibration.phase"):
        calibration_from_dict({"convention": "layoutkit", "phase": ["x", 1]})


# -------------------------------------------------------------------------- Crazyflie firmware
# Re-typed from bitcraze/crazyflie-firmware src/utils/src/lighthouse/lighthouse_calibration.c.
def _cf_model_lh1(x, y, z, c):
    ax, ay = math.atan2(y, x), math.atan2(z, x)
    r = math.sqrt(x * x + y * y)
    comp_tilt = math.asin(min(max(z * math.tan(c["tilt"]) / r, -1.0), 1.0))
    comp_gib = -c["gibmag"] * math.sin(ax + c["gibphase"])
    comp_curve = c["curve"] * ay * ay
    return ax - (comp_tilt + c["phase"] + comp_gib + comp_curve)


def _cf_model_lh2(x, y, z, t, c):
    ax = math.atan2(y, x)
    r = math.sqrt(x * x + y * y)
    base = ax + math.asin(min(max(z * math.tan(t - c["tilt"]) / r, -1.0), 1.0))
    comp_gib = -c["gibmag"] * math.cos(ax + c["gibphase"])
    return base - (c["phase"] + comp_gib)


def _cf_ideal_to_distorted_v1(sw, ideal):
    x, y, z = 1.0, math.tan(ideal[0]), math.tan(ideal[1])
    return (_cf_model_lh1(x, y, z, sw[0]), _cf_model_lh1(x, z, -y, sw[1]))


def _cf_ideal_to_distorted_v2(sw, ideal):
    t30, tan30 = math.pi / 6, 0.5773502691896258
    a1, a2 = ideal
    x, y = 1.0, math.tan((a2 + a1) / 2)
    z = math.sin(a2 - a1) / (tan30 * (math.cos(a2) + math.cos(a1)))
    return (_cf_model_lh2(x, y, z, -t30, sw[0]), _cf_model_lh2(x, y, z, t30, sw[1]))


def _cf_apply(sw, raw, fn):
    est = [raw[0], raw[1]]
    for _ in range(5):
        cur = fn(sw, est)
        d0, d1 = raw[0] - cur[0], raw[1] - cur[1]
        est = [est[0] + d0, est[1] + d1]
        if abs(d0) < 0.0005 and abs(d1) < 0.0005:
            break
    return est


def _cf_sweeps(rng):
    v = _factory(rng)
    names = {"phase": "phase", "tilt": "tilt", "curve": "curve", "gibmag": "gib_mag", "gibphase": "gib_phase",
             "ogeemag": "ogee_mag", "ogeephase": "ogee_phase"}
    return [{cf: float(v[ours][k]) for cf, ours in names.items()} for k in (0, 1)]


@pytest.mark.parametrize("kind", ["lh1", "lh2"])
def test_crazyflie_formula_equals_internal_model(rng, kind):
    """The firmware's idealToDistorted (own parameters; Bitcraze frame x_bc = z, y_bc = x, z_bc = y;
    LH1 angles a = pi/2 - theta, LH2 plane angles as ours) == measure() via calibration_from_crazyflie,
    to 1e-12 rad; and its 5-step / 5e-4 rad fixed-point inverse == undistort() with those settings."""
    for _ in range(5):
        sw = _cf_sweeps(rng)
        cal = calibration_from_crazyflie(sw, kind)
        p = _points(rng)
        ours = measure(p, cal)
        if kind == "lh1":
            ideal_fw = np.column_stack([np.arctan2(p[:, 0], p[:, 2]), np.arctan2(p[:, 1], p[:, 2])])
            ref = np.pi / 2 - np.array([_cf_ideal_to_distorted_v1(sw, a) for a in ideal_fw])
            raw_fw = np.pi / 2 - ours
            inv_ref = np.pi / 2 - np.array([_cf_apply(sw, r, _cf_ideal_to_distorted_v1) for r in raw_fw])
            inv = np.pi / 2 - calibrate_lh1(raw_fw, StationCalibration(tuple(SweepCalibration(**s) for s in sw)),
                                            max_iterations=5, tol=5e-4)
        else:
            ideal_fw = lh2_sweep_angles(p)
            ref = np.array([_cf_ideal_to_distorted_v2(sw, a) for a in ideal_fw])
            inv_ref = np.array([_cf_apply(sw, r, _cf_ideal_to_distorted_v2) for r in ours])
            inv = undistort(ours, cal, max_iterations=5, tol=5e-4)
        np.testing.assert_allclose(ours, ref, rtol=0, atol=1e-12)
        np.testing.assert_allclose(inv, inv_ref, rtol=0, atol=1e-12)
        ideal = sweep_angles(p) if kind == "lh1" else lh2_sweep_angles(p)
        assert np.abs(ours - ideal).max() > 1e-3


def test_firmware_angle_api_round_trip(rng):
    """lh1_model/lh2_model (firmware angle API kept for the decoder) invert with calibrate_lh1/2 to 1e-9;
    the distortion of the ideal angles equals measure() of the ray (distort == measure)."""
    sw = StationCalibration(tuple(SweepCalibration(**s) for s in _cf_sweeps(rng)), 7)
    p = _points(rng, 50)
    a1 = np.column_stack([np.arctan2(p[:, 0], p[:, 2]), np.arctan2(p[:, 1], p[:, 2])])
    np.testing.assert_allclose(calibrate_lh1(lh1_model(a1[:, 0], a1[:, 1], sw), sw), a1, atol=1e-9)
    a2 = lh2_sweep_angles(p)
    np.testing.assert_allclose(calibrate_lh2(lh2_model(a2[:, 0], a2[:, 1], sw), sw), a2, atol=1e-9)
    cal = sw.to_calibration("lh2")
    np.testing.assert_allclose(distort(a2, cal), measure(p, cal), atol=1e-12)
    np.testing.assert_allclose(lh2_to_lh1_angles(a2), sweep_angles(p), atol=1e-12)


# -------------------------------------------------------------------------------- Jacobians
@pytest.mark.parametrize("kind", ["lh1", "lh2"])
@pytest.mark.parametrize("gib", ["ideal", "corrected"])
def test_jacobians_match_finite_differences(rng, kind, gib):
    """d angles / d point and d angles / d params == central differences (h = 1e-6), 1e-6 relative."""
    v = _factory(rng)
    params = np.array([[v[n][k] for n in CALIBRATION_PARAMS] for k in (0, 1)])
    cal = Calibration(params, kind, gib)
    p = _points(rng, 60)
    a, dp, dc = measure_jacobian(p, cal)
    h = 1e-6
    fd_p = np.stack([(measure(p + h * e, cal) - measure(p - h * e, cal)) / (2 * h) for e in np.eye(3)], -1)
    fd_c = np.zeros_like(dc)
    for k in (0, 1):
        for j in range(len(CALIBRATION_PARAMS)):
            up, dn = params.copy(), params.copy()
            up[k, j] += h
            dn[k, j] -= h
            fd_c[:, k, j] = (measure(p, cal.replace(up))[:, k] - measure(p, cal.replace(dn))[:, k]) / (2 * h)
    for ana, fd in ((dp, fd_p), (dc, fd_c)):
        scale = np.abs(fd).max()
        np.testing.assert_allclose(ana, fd, rtol=1e-6, atol=1e-6 * scale)
    if kind == "lh1":
        assert np.all(dc[..., 5:] == 0)
