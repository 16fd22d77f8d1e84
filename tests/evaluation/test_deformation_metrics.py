"""Deformation metrics (paper Table 2 and Supplementary Part 6): known answers on synthetic arrays."""
from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest
from omegaconf import OmegaConf

from conf.metrics_schema import MetricsConfig, validate_metrics
from tasks.core.artifacts import Artifact, ArtifactRef, read_artifact, write_artifact
from tasks.core.params import Params
from tasks.evaluation.deformation_metrics import (
    DEFINITIONS,
    bdc_s,
    bdc_t,
    concordance,
    deformation_metrics,
    deformation_metrics_step,
    finger_trajectories,
    miou,
    nonrigid_displacement,
    physical_figures,
    sdc,
    trajectory_metrics,
    umeyama,
)
from tests.rotations import rotation


def sinusoid(n: int, period: int, shift: int = 0) -> np.ndarray:
    return np.sin(2 * np.pi * (np.arange(n) - shift) / period)


def grid(half: int = 45) -> np.ndarray:
    """Regular unit-spaced grid of points (i, j, 0), |i|, |j| <= half."""
    i, j = np.meshgrid(np.arange(-half, half + 1), np.arange(-half, half + 1), indexing="ij")
    return np.stack([i.ravel(), j.ravel(), np.zeros(i.size)], axis=1).astype(float)


def lens_area(r: float, d: float) -> float:
    """Intersection area of two circles of radius r whose centres are d apart."""
    return 2 * r * r * math.acos(d / (2 * r)) - 0.5 * d * math.sqrt(4 * r * r - d * d)


# ------------------------------------------------------------------------------------------ BDC-T


def test_concordance_known_answers():
    a = 1.0 + sinusoid(100, 20)  # five whole periods
    assert concordance(a, a) == pytest.approx(1.0, abs=1e-12)
    # a shift of s frames of a sinusoid over whole periods: cov = var cos(2 pi s / P), same mean and variance
    assert concordance(a, 1.0 + sinusoid(100, 20, shift=2)) == pytest.approx(math.cos(2 * math.pi * 2 / 20), abs=1e-12)
    # additive white noise of variance sigma^2: 2 var a / (2 var a + sigma^2) = 2*0.5 / (1 + 0.25) = 0.8
    rng = np.random.default_rng(0)
    big = sinusoid(200_000, 20)
    assert concordance(big, big + rng.normal(0.0, 0.5, big.size)) == pytest.approx(0.8, abs=5e-3)
    # a scaled copy of a zero-mean series: 2c / (1 + c^2)
    z = sinusoid(100, 20)
    assert concordance(z, 0.5 * z) == pytest.approx(0.8, abs=1e-12)
    assert concordance(z, 3.0 * z) == pytest.approx(0.6, abs=1e-12)
    # an offset alone lowers it (a correlation would not): 2 var / (2 var + 1^2) with var = 0.5
    assert concordance(z, z + 1.0) == pytest.approx(0.5, abs=1e-12)


def test_bdc_t_averages_clipped_ccc_over_touching_fingers():
    n = 40
    pred = np.zeros((n, 5))
    pred[:, 0] = 0.1 * (1 + sinusoid(n, 20))
    pred[:, 1] = 0.1 * (1 + sinusoid(n, 20))
    obs = pred.copy()
    obs[:, 1] = 0.1 * (1 + sinusoid(n, 20, shift=10))  # half a period late: CCC = -1, clipped to 0
    obs[:, 3] = 0.05  # finger 3 never touches (predicted 0): ignored whatever it observes
    score, per = bdc_t(pred, obs)
    assert per[0] == pytest.approx(1.0) and per[1] == 0.0
    assert np.isnan(per[[2, 3, 4]]).all()
    assert score == pytest.approx(0.5)
    assert math.isnan(bdc_t(np.zeros((n, 5)), obs)[0])  # no finger touches: undefined


# ------------------------------------------------------------------------------------------ SDC


def test_sdc_known_answers():
    n = 60
    c = np.zeros((n, 5))
    c[:, 0] = 0.3 * (1 + sinusoid(n, 20))
    c[:, 1] = c[:, 0]
    c[:, 2] = c[:, 0]
    eps = np.zeros((n, 5))
    eps[:, 0] = 0.02 + 0.4 * c[:, 0]  # affine, positive slope -> 1
    eps[:, 1] = 0.3 * (1 + sinusoid(n, 20, shift=3))  # 3 frames late -> cos(2 pi 3 / 20)
    eps[:, 2] = 0.5 - c[:, 0]  # anti-correlated -> max(0, -1) = 0
    score, per = sdc(c, eps)
    assert per[0] == pytest.approx(1.0, abs=1e-12)
    assert per[1] == pytest.approx(math.cos(2 * math.pi * 3 / 20), abs=1e-12)
    assert per[2] == 0.0
    assert np.isnan(per[3:]).all()  # zero force coefficient: not touching
    assert score == pytest.approx((1.0 + math.cos(2 * math.pi * 3 / 20)) / 3, abs=1e-12)
    # the touching set can be given (the step uses the predicted strain): only finger 1 counts
    only1 = np.array([False, True, False, False, False])
    assert sdc(c, eps, touching=only1)[0] == pytest.approx(math.cos(2 * math.pi * 3 / 20), abs=1e-12)


# ------------------------------------------------------------------------------------------ rigid motion


def test_umeyama_recovers_a_similarity_transform():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(30, 3))
    R = rotation([1, -2, 0.5], 1.1)
    t = np.array([0.3, -0.2, 0.05])
    dst = 2.5 * src @ R.T + t
    s, R_fit, t_fit = umeyama(src, dst, with_scale=True)
    assert s == pytest.approx(2.5, abs=1e-12)
    np.testing.assert_allclose(R_fit, R, atol=1e-12)
    np.testing.assert_allclose(t_fit, t, atol=1e-12)
    s1, R1, _ = umeyama(src, dst, with_scale=False)  # without scale: s = 1, same rotation
    assert s1 == 1.0
    np.testing.assert_allclose(R1, R, atol=1e-12)


def test_umeyama_reflection_fix_returns_the_best_proper_rotation():
    a, b, c = 3.0, 2.0, 1.0
    src = np.array([[a, 0, 0], [-a, 0, 0], [0, b, 0], [0, -b, 0], [0, 0, c], [0, 0, -c]])
    mirror = np.diag([-1.0, 1.0, 1.0])
    dst = src @ mirror  # x -> -x: an improper map
    _, R, t = umeyama(src, dst)
    # Sigma = diag(-a^2, b^2, c^2)/3: the sign flip goes to the smallest singular value (c): R = diag(-1, 1, -1)
    np.testing.assert_allclose(R, np.diag([-1.0, 1.0, -1.0]), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    residual = np.sum((dst - (src @ R.T + t)) ** 2)
    assert residual == pytest.approx(8 * c * c)  # the two +-c points land on each other's place
    # a planar cloud: the mirror image is a rotation by pi about y, reproduced exactly with det R = +1
    planar = src[:4]
    _, R, t = umeyama(planar, planar @ mirror + [0.1, 0.2, 0.3])
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(planar @ R.T + t, planar @ mirror + [0.1, 0.2, 0.3], atol=1e-12)


def test_rigidly_moved_surface_has_zero_nonrigid_displacement():
    rng = np.random.default_rng(2)
    x0 = rng.normal(scale=0.03, size=(200, 3))
    frames = [x0] + [x0 @ rotation([0.2, 1, 0.3], 0.2 * f).T + [0.01 * f, -0.02, 0.005 * f] for f in range(1, 5)]
    u = nonrigid_displacement(np.stack(frames))
    assert np.abs(u).max() < 1e-12
    # a dent on top of the rigid motion is not removed: its displacement survives (most of it)
    dented = np.stack(frames).copy()
    dented[3, :5] += [0.0, 0.0, -0.004]
    assert np.linalg.norm(nonrigid_displacement(dented)[3, :5], axis=1).min() > 0.003


# ------------------------------------------------------------------------------------------ BDC-S, mIoU


def test_bdc_s_disc_against_offset_bump_is_the_lens_ratio():
    x = grid()
    r, d = 20.0, 10.0
    A = np.linalg.norm(x, axis=1) <= r
    u = np.zeros((2, len(x), 3))
    for f, offset in enumerate((d, 0.0)):
        u[f, :, 2] = np.exp(-((x[:, 0] - offset) ** 2 + x[:, 1] ** 2) / (2 * 15.0 ** 2))
    constrained = np.stack([A, A, np.zeros_like(A)])
    u = np.concatenate([u, np.zeros((1, len(x), 3))])
    score, iou = bdc_s(constrained, u)
    lens = lens_area(r, d)
    expected = lens / (2 * math.pi * r * r - lens)  # 0.521 for d = r / 2
    assert iou[0] == pytest.approx(expected, abs=0.01)  # grid: 0.5246
    assert iou[1] == 1.0  # bump centred on the disc: the top-|A| points are the disc itself
    assert math.isnan(iou[2])  # no constrained point: frame not counted
    assert score == pytest.approx((iou[0] + 1.0) / 2)


def test_miou_of_a_halved_gaussian_bump_is_the_ratio_of_disc_areas():
    x = grid()
    sigma, f = 12.0, 0.1
    bump = np.exp(-(x[:, 0] ** 2 + x[:, 1] ** 2) / (2 * sigma ** 2))
    prescribed = np.zeros((3, len(x), 3))
    prescribed[0, :, 2] = prescribed[1, :, 2] = 0.002 * bump
    observed = prescribed.copy()
    observed[1] *= 0.5
    score, iou = miou(prescribed, observed, f)
    assert iou[0] == 1.0
    # bump >= f  <=>  rho^2 <= 2 sigma^2 ln(1/f); 0.5 bump >= f  <=>  rho^2 <= 2 sigma^2 ln(0.5/f); O inside I
    assert iou[1] == pytest.approx(math.log(0.5 / f) / math.log(1 / f), abs=2e-3)  # 0.699; grid: 0.6988
    assert math.isnan(iou[2])  # nothing prescribed
    assert score == pytest.approx((1.0 + iou[1]) / 2)


# ------------------------------------------------------------------------------------------ trajectories


def one_finger(dp: np.ndarray, dq: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(T, 3) trajectories as finger 2 of (T, 5, 3) arrays; only finger 2 in contact, all frames."""
    P, Q = np.full((len(dp), 5, 3), np.nan), np.full((len(dp), 5, 3), np.nan)
    P[:, 2], Q[:, 2] = dp, dq
    contact = np.zeros((len(dp), 5), bool)
    contact[:, 2] = True
    return P, Q, contact


def lissajous(n: int = 41) -> np.ndarray:
    s = np.arange(n) / (n - 1)
    return 0.01 * np.stack([np.sin(2 * np.pi * s), np.cos(3 * np.pi * s) - 1, s ** 2], axis=1)


def test_trajectory_metrics_known_answers():
    dp = lissajous()
    m = trajectory_metrics(*one_finger(dp, dp), frame_dt=1 / 30)
    assert (m["ate"], m["mte"], m["tce"], m["cosine_similarity"]) == pytest.approx((0.0, 0.0, 0.0, 1.0), abs=1e-12)
    assert (m["n_points"], m["n_pairs"]) == (41, 40)
    # a pure translation: aligned away (ATE 0), MTE = |c|
    c = np.array([0.003, -0.004, 0.0])
    m = trajectory_metrics(*one_finger(dp, dp + c), frame_dt=1 / 30)
    assert m["ate"] == pytest.approx(0.0, abs=1e-12) and m["mte"] == pytest.approx(0.005, abs=1e-12)
    assert m["tce"] == pytest.approx(0.0, abs=1e-12)
    # a rigid motion: ATE 0
    R = rotation([1, 1, 0], 0.7)
    assert trajectory_metrics(*one_finger(dp, dp @ R.T + c), frame_dt=1 / 30)["ate"] == pytest.approx(0.0, abs=1e-12)
    # a scaled copy: ATE 0 only when the alignment fits a scale
    half = 0.5 * dp @ R.T + c
    assert trajectory_metrics(*one_finger(dp, half), frame_dt=1 / 30, ate_with_scale=True)["ate"] == pytest.approx(
        0.0, abs=1e-12)
    assert trajectory_metrics(*one_finger(dp, half), frame_dt=1 / 30)["ate"] > 1e-4
    # opposite motion: cosine -1
    assert trajectory_metrics(*one_finger(dp, -dp), frame_dt=1 / 30)["cosine_similarity"] == pytest.approx(-1.0)


def test_time_consistency_error_of_a_one_frame_delay():
    A, P, h = 0.004, 12, 1 / 30  # amplitude m, period frames, frame step s
    n = 3 * P + 1  # consecutive pairs cover three whole periods
    e = np.array([2.0, -1.0, 2.0]) / 3.0
    dp = A * sinusoid(n, P)[:, None] * e
    dq = A * sinusoid(n, P, shift=1)[:, None] * e  # the reconstruction lags one frame
    m = trajectory_metrics(*one_finger(dp, dq), frame_dt=h)
    # e_n = p(n+1) - 2 p(n) + p(n-1) = -4 A sin^2(pi/P) sin(2 pi n/P): RMS = 4 A sin^2(pi/P) / sqrt(2)
    assert m["tce"] == pytest.approx(2 * math.sqrt(2) * A * math.sin(math.pi / P) ** 2 / h, rel=1e-9)


def test_cosine_similarity_skips_increments_below_min_motion():
    dp = np.zeros((4, 3))
    dp[:, 0] = [0.0, 1e-3, 2e-3, 2e-3 + 1e-7]  # the last increment is jitter
    dq = dp.copy()
    dq[3, 0] -= 2e-7  # ... in the opposite direction
    m = trajectory_metrics(*one_finger(dp, dq), frame_dt=0.1, min_motion=1e-5)
    assert m["cosine_similarity"] == pytest.approx(1.0) and m["n_cosine_pairs"] == 2
    assert trajectory_metrics(*one_finger(dp, dq), frame_dt=0.1, min_motion=0.0)["cosine_similarity"] == \
        pytest.approx(1 / 3)


def test_finger_trajectories_start_at_first_contact_and_are_nan_outside():
    T, S = 6, 4
    tips = np.zeros((T, 5, 3))
    tips[:, 1, 0] = -0.001 * np.arange(T)  # the index finger pushes along -x, 1 mm per frame
    x = np.zeros((T, S, 3))
    x[:, :2, 0] = 0.03 - 0.001 * np.arange(T)[:, None]  # its two region points follow it
    region = np.zeros((5, S), bool)
    region[1, :2] = True
    contact = np.zeros((T, 5), bool)
    contact[2:5, 1] = True
    dp, dq = finger_trajectories(tips, x, region, contact)
    np.testing.assert_allclose(dp[2:5, 1, 0], [0.0, -0.001, -0.002], atol=1e-15)
    np.testing.assert_allclose(dq[2:5, 1], dp[2:5, 1], atol=1e-15)
    assert np.isnan(dp[[0, 1, 5], 1]).all() and np.isnan(dq[:, [0, 2, 3, 4]]).all()


# ------------------------------------------------------------------------------------------ physical figures


def test_physical_figures_known_values():
    T = 4
    J = np.ones((T, 3))
    J[2] = [1.0, 1.0, 0.5]  # v0 = (1, 1, 2): (1 + 1 + 1) / 4 = 0.75
    strain = np.zeros((T, 5))
    strain[:, 1] = [0.0, 0.1, 0.2, 0.05]
    strain[:, 2] = [0.0, 0.15, 0.0, 0.0]
    reaction = np.zeros((T, 5, 3))
    reaction[1, 1] = [3.0, 4.0, 0.0]
    feedback = np.zeros((T, 5))
    feedback[2, 1] = 2.5
    contact_ke_ie = np.array([0.2, 0.05])  # the check's measure, one value per judged contact
    s, per, ratio = physical_figures(J, [1.0, 1.0, 2.0], strain, reaction, np.zeros_like(reaction), feedback,
                                     contact_ke_ie, 0.25, {"crossed": False, "threshold": 0.3})
    np.testing.assert_allclose(ratio, [1.0, 1.0, 0.75, 1.0])
    assert s["max_volume_change"] == pytest.approx(0.25)
    assert s["max_squeeze_strain"] == pytest.approx(0.2)
    assert s["rebound_ratio"] == pytest.approx(1 - 0.05 / 0.2)
    assert s["max_ke_ie_in_contact"] == pytest.approx(0.2) and s["quasi_static_warned"] == 0.0  # 0.2 <= 0.25
    s, _, _ = physical_figures(J, [1.0, 1.0, 2.0], strain, reaction, reaction, feedback, contact_ke_ie, 0.1, None)
    assert s["max_ke_ie_in_contact"] == pytest.approx(0.2) and s["quasi_static_warned"] == 1.0  # 0.2 > 0.1: warned
    assert math.isnan(s["threshold_time"])
    assert per["peak_reaction_force"][1] == pytest.approx(5.0) and per["peak_feedback_force"][1] == 2.5
    s, _, _ = physical_figures(J, [1.0, 1.0, 2.0], 0 * strain, reaction, reaction, feedback, np.zeros(0), 0.25,
                               {"crossed": True, "time": 0.4})
    assert math.isnan(s["rebound_ratio"]) and s["threshold_time"] == 0.4
    assert math.isnan(s["max_ke_ie_in_contact"]) and math.isnan(s["quasi_static_warned"])  # no contact judged
    s, _, _ = physical_figures(J, [1.0, 1.0, 2.0], strain, reaction, reaction, feedback, np.array([0.01, np.nan]),
                               0.25, None)  # NaN: a contact with kinetic but no internal energy
    assert math.isnan(s["max_ke_ie_in_contact"]) and s["quasi_static_warned"] == 1.0


# ------------------------------------------------------------------------------------------ errors and config


@pytest.mark.parametrize("call, message", [
    (lambda: bdc_t(np.zeros((10, 4)), np.zeros((10, 4))), "predicted_squeeze_strain must have shape (n, 5), got (10, 4)"),
    (lambda: bdc_t(np.zeros((10, 5)), np.zeros((9, 5))), "squeeze_strain must have shape (10, 5), got (9, 5)"),
    (lambda: umeyama(np.zeros((4, 3)), np.zeros((5, 3))), "dst must have shape (4, 3), got (5, 3)"),
    (lambda: nonrigid_displacement(np.zeros((3, 7, 2))), "gaussian_positions must have shape (n, n, 3), got (3, 7, 2)"),
    (lambda: bdc_s(np.zeros((3, 7), bool), np.zeros((3, 6, 3))), "u_obs must have shape (3, 7, 3), got (3, 6, 3)"),
    (lambda: miou(np.zeros((3, 7, 3)), np.zeros((3, 7, 3)), 1.5), "region_fraction must be in (0, 1), got 1.5"),
    (lambda: trajectory_metrics(np.zeros((3, 5, 3)), np.zeros((3, 5, 3)), np.zeros((3, 5), bool), 0.0),
     "frame_dt must be > 0 s"),
])
def test_bad_shapes_are_one_line_value_errors(call, message):
    with pytest.raises(ValueError) as err:
        call()
    assert str(err.value).startswith(message) and "\n" not in str(err.value)


def test_metrics_config_validation():
    assert validate_metrics(None) == MetricsConfig()
    node = OmegaConf.structured(MetricsConfig(region_fraction=0.2))
    assert validate_metrics(node).region_fraction == 0.2
    for bad, key in [({"region_fraction": 0.0}, "metrics.region_fraction: must be in (0, 1)"),
                     ({"region_fraction": 1.0}, "metrics.region_fraction: must be in (0, 1)"),
                     ({"min_motion": -1e-6}, "metrics.min_motion: must be a finite length >= 0 m"),
                     ({"ate_with_scale": "yes"}, "metrics.ate_with_scale: must be true or false"),
                     ({"fraction": 0.1}, "metrics: unknown keys ['fraction']")]:
        with pytest.raises(ValueError, match=re.escape(key)):
            validate_metrics(bad)


# ------------------------------------------------------------------------------------------ the whole step


def synthetic_artifacts(contact: bool) -> dict[str, dict]:
    """Arrays shaped like the real artifacts: a 3 cm sphere pressed by the index finger from +x."""
    T, S, K, P_shell, P_int = 12, 150, 5, 40, 10
    i = np.arange(S) + 0.5
    polar, azim = np.arccos(1 - 2 * i / S), np.pi * (1 + 5 ** 0.5) * i
    n = np.stack([np.sin(polar) * np.cos(azim), np.sin(polar) * np.sin(azim), np.cos(polar)], axis=1)
    surface = 0.03 * n
    time = np.arange(T) / 30.0
    active = np.zeros((T, K), bool)
    if contact:
        active[2:11, 1] = True  # the frames in which the flexion gives c > 0
    coeff = np.zeros((T, K))
    coeff[:, 1] = np.clip(np.sin(np.pi * (np.arange(T) - 1) / 10), 0, None)  # flexion, also without contact
    weight = np.exp(-np.sum((surface - [0.03, 0, 0]) ** 2, axis=1) / (2 * 0.01 ** 2))
    constrained = active[:, 1, None] & (weight >= 0.05)[None, :]
    disp = np.zeros((T, S, 3))
    disp[..., 0] = -0.004 * (coeff[:, 1, None] * active[:, 1, None]) * weight * constrained
    normals = np.zeros((T, K, 3))
    normals[:, 1] = [1.0, 0.0, 0.0]
    predicted = np.zeros((T, K))
    predicted[:, 1] = 0.004 * coeff[:, 1] * active[:, 1] / 0.03
    observed = 0.8 * predicted  # the simulation reaches 80 % of the prescribed strain
    gpos = surface + 0.8 * disp
    tips = np.zeros((T, K, 3))
    tips[:, 1] = [0.035, 0.0, 0.0]
    tips[:, 1, 0] -= 0.004 * coeff[:, 1] * active[:, 1]
    J = np.ones((T, P_shell + P_int))
    J[:, :P_shell] -= 0.01 * coeff[:, 1, None]
    rollout = {
        "squeeze_strain": observed, "predicted_squeeze_strain": predicted, "gaussian_positions": gpos,
        "reaction_force": np.zeros((T, K, 3)) + 0.5 * coeff[:, :, None], "applied_force": np.zeros((T, K, 3)),
        "feedback_force": 2.0 * coeff * active, "particle_J": J, "kinetic_energy": np.zeros(T),
        "internal_energy": np.zeros(T), "ke_ie_ratio": 0.01 * coeff[:, 1], "released": np.zeros(P_shell + P_int, bool),
        "ke_ie_contact": np.where(active[:, 1], 0.01 * coeff[:, 1], np.nan),
    }
    contacts = [{"first_frame": 2, "last_frame": 10, "ke_ie": 0.01 * float(coeff[2:11, 1].max())}] if contact else []
    return {
        "rollout": rollout,
        "rollout_attrs": {"boundary": "dirichlet", "n_interior": P_int, "quasi_static": {"limit": 0.1, "contacts": contacts},
                          "threshold_event": {"crossed": True, "time": float(time[6]), "threshold": 0.1}},
        "field": {"displacement": disp, "weight": weight[None].repeat(T, 0) * constrained, "constrained": constrained,
                  "finger": np.where(constrained, 1, -1), "surface_points": surface},
        "forces": {"force_coefficients": coeff},
        "contacts": {"patch_active": active, "patch_normals": normals, "patch_areas": 1e-4 * active},
        "frames": {"time": time, "fingertip_positions": tips},
        "obj": {"particle_volumes": np.full(P_shell, 1e-7), "interior_volumes": np.full(P_int, 2e-7)},
    }


def test_deformation_metrics_on_a_synthetic_session():
    art = synthetic_artifacts(contact=True)
    arrays, attrs = deformation_metrics(**art, params={"region_fraction": 0.1, "ate_with_scale": False,
                                                       "min_motion": 1e-5})
    m = attrs["metrics"]
    for name in ("bdc_t", "bdc_s", "sdc", "miou"):
        assert 0.0 <= m[name] <= 1.0, name
    assert m["sdc"] == pytest.approx(1.0, abs=1e-9)  # observed strain proportional to c: Pearson 1
    a = art["rollout"]["predicted_squeeze_strain"][:, 1]  # b = 0.8 a: CCC = 1.6 var a / (1.64 var a + 0.04 mean^2)
    assert m["bdc_t"] == pytest.approx(1.6 * a.var() / (1.64 * a.var() + 0.04 * a.mean() ** 2), abs=1e-6)
    for name in ("ate", "mte", "tce"):
        assert m[name] is not None and m[name] >= 0.0, name
    assert -1.0 <= m["cosine_similarity"] <= 1.0
    assert m["threshold_time"] == pytest.approx(0.2)
    # 40 shell particles of 1e-7 m^3 at J = 1 - 0.01 c, 10 interior particles of 2e-7 at J = 1
    c = art["forces"]["force_coefficients"][:, 1]
    np.testing.assert_allclose(arrays["volume_ratio"].data, 1 - 0.01 * c * 4e-6 / 6e-6)
    assert m["max_volume_change"] == pytest.approx(0.01 * c.max() * 2 / 3)
    # the quasi-static check's measure over the contact it judged, below its limit 0.1
    assert m["max_ke_ie_in_contact"] == pytest.approx(0.01 * c[2:11].max()) and m["quasi_static_warned"] == 0.0
    # per-frame series: defined exactly where their frames are
    assert np.isfinite(arrays["bdc_s_iou"].data[2:11]).all() and np.isnan(arrays["bdc_s_iou"].data[[0, 1, 11]]).all()
    traj = arrays["sensed_trajectory"].data
    assert np.isfinite(traj[2:11, 1]).all() and np.isnan(traj[:2]).all() and np.isnan(traj[:, 0]).all()
    assert arrays["reconstructed_trajectory"].dims == ("frame", "finger", "xyz")
    assert arrays["nonrigid_displacement_rms"].units == "m"
    assert attrs["per_finger"]["bdc_t"][0] is None and attrs["per_finger"]["bdc_t"][1] == pytest.approx(m["bdc_t"])
    assert attrs["definitions"] == DEFINITIONS and attrs["no_contact"] is False
    json.dumps(attrs, allow_nan=False)


def test_deformation_metrics_without_contact_are_nan_not_errors():
    arrays, attrs = deformation_metrics(**synthetic_artifacts(contact=False), params=None)
    m = attrs["metrics"]
    for name in ("bdc_t", "bdc_s", "sdc", "miou", "ate", "mte", "tce", "cosine_similarity", "max_ke_ie_in_contact",
                 "quasi_static_warned"):
        assert m[name] is None, name
    assert attrs["no_contact"] is True and attrs["counts"]["trajectory_points"] == 0
    assert np.isnan(arrays["sensed_trajectory"].data).all() and np.isnan(arrays["miou_iou"].data).all()
    json.dumps(attrs, allow_nan=False)


def test_step_compute_runs_on_loaded_artifacts_and_writes(tmp_path):
    art = synthetic_artifacts(contact=True)

    def loaded(step: str, arrays: dict, attrs: dict | None = None) -> Artifact:
        ref = ArtifactRef(rel=step, digest="0" * 64, step=step, scope="synthetic").at(tmp_path)
        return Artifact(ref=ref, arrays=arrays, dims={}, units={}, attrs=attrs or {})

    inputs = {"mpm_rollout": loaded("mpm_rollout", art["rollout"], art["rollout_attrs"]),
              "dirichlet_field": loaded("dirichlet_field", art["field"]),
              "force_coefficients": loaded("force_coefficients", art["forces"]),
              "contact_patches": loaded("contact_patches", art["contacts"]),
              "signal_smoothing": loaded("signal_smoothing", art["frames"]),
              "mpm_particles": loaded("mpm_particles", art["obj"])}
    params = Params("deformation_metrics", {"metrics": {"region_fraction": 0.1, "ate_with_scale": False,
                                                        "min_motion": 1e-5}})
    arrays, attrs = deformation_metrics_step.compute(inputs, params)
    direct = deformation_metrics(**art, params=None)
    assert attrs == direct[1]
    ref = write_artifact(tmp_path / "metrics.zarr", arrays, step="deformation_metrics", scope="synthetic",
                         config_digest="x", attrs=attrs)
    back = read_artifact(ref)
    np.testing.assert_array_equal(back["bdc_s_iou"], arrays["bdc_s_iou"].data)  # NaNs survive the round trip
    assert back.attrs["metrics"] == attrs["metrics"]
