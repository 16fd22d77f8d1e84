"""Known-answer tests for the squeezing control signals (paper sec. "Squeezing Control Mapping", eq. 1)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from conf.schema import ForceConfig, SignalConfig, SmoothingConfig
from tasks.control.force_coefficients import force_coefficients, loading_curve
from tasks.control.recording import (
    PERCENT_BENT_FULL_SCALE,
    REQUIRED_COLUMNS,
    SignalError,
    read_recording,
    write_recording,
)
from tasks.control.signal_smoothing import ema, resample_antialiased, smooth_signals
from tasks.control.squeeze_signals import SESSION_KINDS, grasp_targets, synthesize_session
from tasks.core.artifacts import Array

RADIUS, HEIGHT = 0.033, 0.12  # soda can, m


# ------------------------------------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def can_surface():
    """Side of a cylinder (radius 33 mm, height 120 mm) + caps, outward normals, deterministic."""
    rng = np.random.default_rng(123)
    th = rng.uniform(0, 2 * np.pi, 2500)
    z = rng.uniform(-HEIGHT / 2, HEIGHT / 2, 2500)
    side = np.stack([RADIUS * np.cos(th), RADIUS * np.sin(th), z], 1)
    side_n = np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], 1)
    r = RADIUS * np.sqrt(rng.uniform(0, 1, 500))
    ph = rng.uniform(0, 2 * np.pi, 500)
    zc = np.where(np.arange(500) % 2 == 0, HEIGHT / 2, -HEIGHT / 2)
    caps = np.stack([r * np.cos(ph), r * np.sin(ph), zc], 1)
    caps_n = np.stack([np.zeros(500), np.zeros(500), np.sign(zc)], 1)
    return np.vstack([side, caps]), np.vstack([side_n, caps_n])


@pytest.fixture(scope="module")
def sessions(can_surface):
    pts, nrm = can_surface
    cfg = SignalConfig()
    return {kind: synthesize_session(kind, pts, nrm, cfg) for kind in SESSION_KINDS}


def _force(u, frame_rate=30.0, cfg: ForceConfig | None = None, **over):
    cfg = cfg or ForceConfig()
    kw = dict(weights=cfg.weights, beta=cfg.beta, gamma=cfg.gamma, release_gamma=cfg.release_gamma,
              release_rate_threshold=cfg.release_rate_threshold)
    kw.update(over)
    return force_coefficients(np.asarray(u, float), frame_rate, **kw)


def _raw(time, flex, tips=None, palm=None, quat=None):
    n = len(time)
    return {
        "time": np.asarray(time, float),
        "flexion": np.asarray(flex, float),
        "fingertip_positions": np.zeros((n, 5, 3)) + np.arange(5)[None, :, None] * 0.01 + [0.05, 0, 0]
        if tips is None else tips,
        "palm_position": np.zeros((n, 3)) + [0, -0.05, 0] if palm is None else palm,
        "palm_orientation": np.tile([1.0, 0, 0, 0], (n, 1)) if quat is None else quat,
    }


# ------------------------------------------------------------------------------------------------ eq. 1
def test_eq1_known_answers_and_threshold():
    u = np.tile([0.55, 0.30, 0.05, 0.02, 1.0], (4, 1))
    out = _force(u, weights=[1.2, 1.0, 1.0, 1.0, 0.5], beta=0.05, gamma=2.0)
    c = out["force_coefficients"].data
    np.testing.assert_allclose(c[0], [1.2 * 0.25, 0.0625, 0.0, 0.0, 0.5 * 0.95**2], atol=1e-15)
    assert c[0, 0] == pytest.approx(0.3)
    assert out["phase"].data.dtype == np.int8
    np.testing.assert_array_equal(out["phase"].data[0], [1, 1, 0, 0, 1])
    assert loading_curve(0.55, 1.2, 0.05, 2.0) == pytest.approx(0.3)
    assert loading_curve(0.04, 1.2, 0.05, 2.0) == 0.0
    # fractional gamma
    c2 = _force(np.full((3, 5), 0.30), weights=[1.0] * 5, beta=0.05, gamma=1.5)["force_coefficients"].data
    np.testing.assert_allclose(c2, 0.25**1.5)
    assert isinstance(out["force_coefficients"], Array)
    assert tuple(out["force_coefficients"].dims) == ("frame", "finger")


def _ramp_profile(fr=30.0):
    up = np.linspace(0.0, 0.8, int(fr))  # 1 s up
    hold = np.full(int(fr / 2), 0.8)
    down = np.linspace(0.8, 0.0, int(fr))[1:]  # 1 s down
    tail = np.zeros(10)
    return np.concatenate([up, hold, down, tail])


def test_release_curve_continuous_and_zero_at_beta():
    fr, beta, gamma, rg = 30.0, 0.05, 1.5, 3.0
    u1 = _ramp_profile(fr)
    u = np.tile(u1[:, None], (1, 5))
    out = _force(u, fr, weights=[1.0] * 5, beta=beta, gamma=gamma, release_gamma=rg, release_rate_threshold=0.05)
    c, ph = out["force_coefficients"].data[:, 1], out["phase"].data[:, 1]
    rel = np.flatnonzero(ph == -1)
    assert rel.size > 10
    s = rel[0]
    u_pk, c_pk = u1[s - 1], c[s - 1]
    assert c_pk == pytest.approx(loading_curve(u_pk, 1.0, beta, gamma))  # loading curve before the switch
    expected = c_pk * (np.maximum(u1[rel] - beta, 0) / (u_pk - beta)) ** rg
    np.testing.assert_allclose(c[rel], expected, rtol=1e-12, atol=1e-15)
    # continuity at the switch: the jump is no larger than one frame of the loading curve's slope
    max_load_step = np.max(np.abs(np.diff(loading_curve(u1[: s], 1.0, beta, gamma))))
    assert abs(c[s] - c[s - 1]) <= max_load_step
    # release is below the loading curve (hysteresis, rg > gamma) and 0 at/below beta
    assert np.all(c[rel] <= loading_curve(u1[rel], 1.0, beta, gamma) + 1e-12)
    assert np.all(c[u1 <= beta] == 0.0)
    assert np.all(ph[u1 <= beta] == 0)
    assert c[-1] == 0.0


def _reload_profile(t):
    """0 -> 0.6 (1 s), hold, 0.6 -> 0.3 (0.5 s), hold, 0.3 -> 0.9 (1 s), hold (flexion, 1)."""
    knots_t = [0.0, 1.0, 1.2, 1.7, 1.9, 2.9, 3.1]
    knots_u = [0.0, 0.6, 0.6, 0.3, 0.3, 0.9, 0.9]
    return np.interp(t, knots_t, knots_u)


def test_reload_after_partial_release_is_continuous_and_rejoins_eq1():
    beta, gamma = 0.05, 1.5
    steps = {}
    for fr in (30.0, 120.0):
        t = np.arange(0, 3.1 + 1e-9, 1 / fr)
        u1 = _reload_profile(t)
        out = _force(np.tile(u1[:, None], (1, 5)), fr, weights=[1.0] * 5, beta=beta, gamma=gamma,
                     release_gamma=2.5, release_rate_threshold=0.05)
        c, ph = out["force_coefficients"].data[:, 0], out["phase"].data[:, 0]
        assert (ph == -1).any() and (ph == 1).any()
        assert np.all(ph[(t > 1.25) & (t < 1.65)] == -1)
        load = loading_curve(u1, 1.0, beta, gamma)
        assert np.all(c <= load + 1e-12)  # hysteresis: never above eq. 1
        back_on = (t > 2.0) & (u1 >= 0.6 + 1e-9)
        np.testing.assert_allclose(c[back_on], load[back_on])  # eq. 1 again above the old peak
        hold = (t > 1.75) & (t < 1.85)
        assert np.ptp(c[hold]) < 1e-12  # a hold after a partial release keeps its force
        steps[fr] = np.max(np.abs(np.diff(c)))
        assert steps[fr] < 2.0 * np.max(np.abs(np.diff(load)))
    # continuity: 4x finer sampling gives ~4x smaller steps (a jump would not shrink)
    assert steps[120.0] < 0.35 * steps[30.0]


@pytest.mark.parametrize(
    "over, key",
    [
        (dict(weights=[1.0, 1.0, 1.0]), "control.force.weights"),
        (dict(beta=1.0), "control.force.beta"),
        (dict(beta=-0.1), "control.force.beta"),
        (dict(gamma=-1.0), "control.force.gamma must be > 0, got -1"),
        (dict(release_gamma=0.0), "control.force.release_gamma"),
        (dict(release_rate_threshold=-1.0), "control.force.release_rate_threshold"),
    ],
)
def test_force_config_validation(over, key):
    with pytest.raises(ValueError) as err:
        _force(np.zeros((4, 5)), **over)
    assert key in str(err.value) and "\n" not in str(err.value)


# ------------------------------------------------------------------------------------------------ smoothing
def test_ema_step_known_answer():
    alpha = 0.35
    x = np.concatenate([np.zeros(5), np.ones(20)])
    y = ema(x, alpha)
    n = np.arange(1, 21)
    np.testing.assert_allclose(y[5:], 1 - (1 - alpha) ** n, rtol=1e-12)
    assert np.all(y[:5] == 0)
    np.testing.assert_array_equal(ema(x, 1.0), x)


def test_resampling_linear_ramp_exact_on_jittered_samples():
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.5e-3, 1.5e-3, 3000))  # ~1 kHz, non-uniform, ~3 s
    t -= t[0]
    tips = (0.01 + 0.02 * t)[:, None, None] * np.ones((1, 5, 3))
    flex = np.tile((0.1 + 0.2 * t)[:, None], (1, 5))
    raw = _raw(t, flex, tips=tips)
    out = smooth_signals(raw, 30.0, 1.0, 0.0)  # alpha 1: no EMA; rest 0: no de-bias
    tf = out["time"].data
    np.testing.assert_allclose(tf, t[0] + np.arange(len(tf)) / 30.0)
    np.testing.assert_allclose(out["flexion_raw"].data, np.tile((0.1 + 0.2 * tf)[:, None], (1, 5)), atol=1e-12)
    np.testing.assert_allclose(out["flexion"].data, out["flexion_raw"].data, atol=1e-12)
    np.testing.assert_allclose(out["fingertip_positions"].data[:, 2, 1], 0.01 + 0.02 * tf, atol=1e-12)


@pytest.mark.parametrize("freq", [300.0, 290.0, 45.0])
def test_antialiasing_removes_high_frequency(freq):
    t = np.arange(0, 4.0, 1e-3)  # 1 kHz
    x = 0.5 + 0.4 * np.cos(2 * np.pi * freq * t + 0.3)
    tf = np.arange(0, 4.0 + 1e-9, 1 / 30)
    y = resample_antialiased(t, x[:, None], tf, 1 / 30)[:, 0]
    naive = np.interp(tf, t, x)
    inner = slice(1, -1)
    assert np.max(np.abs(naive[inner] - 0.5)) > 0.1  # point sampling aliases
    assert np.max(np.abs(y[inner] - 0.5)) < 0.05 * 0.4  # > 95 % removed


def test_debias_removes_constant_offset():
    fr = 30.0
    t = np.arange(0, 3.0, 1e-3)
    signal = np.where(t < 1.0, 0.0, np.minimum((t - 1.0) * 0.5, 0.6))
    offsets = np.array([0.1, 0.05, 0.2, 0.0, 0.12])
    flex = signal[:, None] + offsets
    out = smooth_signals(_raw(t, flex), fr, 0.35, 0.5)
    np.testing.assert_allclose(out["rest_flexion"].data, offsets, atol=1e-12)
    clean = smooth_signals(_raw(t, np.tile(signal[:, None], (1, 5))), fr, 0.35, 0.5)
    np.testing.assert_allclose(out["flexion"].data, clean["flexion"].data, atol=1e-9)
    assert np.all(out["flexion"].data[out["time"].data < 0.9] < 1e-12)


def test_smoothing_arrays_and_units(sessions):
    sm = SmoothingConfig()
    out = smooth_signals(sessions["ramp_hold_release"], sm.frame_rate, sm.ema_alpha, sm.rest_window)
    nfr = len(out["time"].data)
    assert nfr == int(np.floor(3.0 * 30 + 1e-9)) + 1
    spec = {
        "time": (("frame",), "s", (nfr,)),
        "flexion": (("frame", "finger"), "1", (nfr, 5)),
        "flexion_raw": (("frame", "finger"), "1", (nfr, 5)),
        "fingertip_positions": (("frame", "finger", "xyz"), "m", (nfr, 5, 3)),
        "squeeze_directions": (("frame", "finger", "xyz"), "1", (nfr, 5, 3)),
        "palm_position": (("frame", "xyz"), "m", (nfr, 3)),
        "palm_orientation": (("frame", "quat"), "1", (nfr, 4)),
    }
    for name, (dims, units, shape) in spec.items():
        a = out[name]
        assert isinstance(a, Array) and tuple(a.dims) == dims and a.units == units and a.data.shape == shape, name
    u = out["flexion"].data
    assert u.min() >= 0 and u.max() <= 1
    np.testing.assert_allclose(np.linalg.norm(out["palm_orientation"].data, axis=1), 1.0)


def test_quaternion_sign_flips_do_not_break_smoothing():
    t = np.arange(0, 1.0, 1e-2)
    q0 = np.array([0.9, 0.1, -0.3, 0.2])
    q0 /= np.linalg.norm(q0)
    quat = np.where((np.arange(len(t)) % 2 == 0)[:, None], q0, -q0)  # same rotation, alternating sign
    out = smooth_signals(_raw(t, np.full((len(t), 5), 0.1), quat=quat), 30.0, 0.35, 0.2)
    np.testing.assert_allclose(out["palm_orientation"].data, np.tile(q0, (len(out["time"].data), 1)), atol=1e-12)


@pytest.mark.parametrize(
    "args, key",
    [((0.0, 0.35, 0.2), "control.smoothing.frame_rate"), ((30.0, 0.0, 0.2), "control.smoothing.ema_alpha"),
     ((30.0, 1.5, 0.2), "control.smoothing.ema_alpha"), ((30.0, 0.35, -1.0), "control.smoothing.rest_window"),
     ((30.0, 0.35, 5.0), "control.smoothing.rest_window")],
)
def test_smoothing_config_validation(args, key):
    t = np.arange(0, 1.0, 1e-2)
    with pytest.raises(ValueError) as err:
        smooth_signals(_raw(t, np.zeros((len(t), 5))), *args)
    assert key in str(err.value)


def test_squeeze_directions_unit_and_toward_object(sessions, can_surface):
    pts, nrm = can_surface
    targets = grasp_targets(pts, nrm)
    for kind, raw in sessions.items():
        for ref in ("grasp_centre", "grasp_axis"):
            out = smooth_signals(raw, 30.0, 0.35, 0.2, direction_reference=ref)
            a = out["squeeze_directions"].data
            p = out["fingertip_positions"].data
            np.testing.assert_allclose(np.linalg.norm(a, axis=-1), 1.0, atol=1e-12)
            to_centre = -p / np.linalg.norm(p, axis=-1, keepdims=True)  # object centred at the origin
            assert np.all(np.einsum("fkc,fkc->fk", a, to_centre) > 0.5), (kind, ref)
            assert np.all(np.einsum("fkc,kc->fk", a, -targets["normals"]) > 0.5), (kind, ref)
            g = out["grasp_centre"].data
            np.testing.assert_allclose(g, (p.sum(1) + out["palm_position"].data) / 6)


# ------------------------------------------------------------------------------------------------ synthesis
def test_synthetic_sessions_deterministic_per_seed(can_surface):
    pts, nrm = can_surface
    cfg = SignalConfig(seed=7)
    a = synthesize_session("pulses", pts, nrm, cfg)
    b = synthesize_session("pulses", pts, nrm, cfg)
    c = synthesize_session("pulses", pts, nrm, replace(cfg, seed=8))
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    assert not np.allclose(a["flexion"], c["flexion"])
    assert not np.allclose(a["fingertip_positions"], c["fingertip_positions"])
    # mapping configs work too
    d = synthesize_session("pulses", pts, nrm, {"seed": 7, "duration": 3.0, "sensor_rate": 200.0})
    np.testing.assert_array_equal(a["flexion"], d["flexion"])


def test_synthetic_sampling_and_ranges(sessions):
    cfg = SignalConfig()
    n = int(cfg.duration * cfg.sensor_rate) + 1
    for kind, s in sessions.items():
        assert s["time"].shape == (n,)
        np.testing.assert_allclose(np.diff(s["time"]), 1 / cfg.sensor_rate)
        assert s["flexion"].shape == (n, 5) and s["fingertip_positions"].shape == (n, 5, 3)
        assert s["palm_position"].shape == (n, 3) and s["palm_orientation"].shape == (n, 4)
        assert s["flexion"].min() >= 0 and s["flexion"].max() <= 1
        assert abs(s["flexion"].max() - cfg.peak_flexion) < 0.06, kind
        np.testing.assert_allclose(np.linalg.norm(s["palm_orientation"], axis=1), 1.0)


def _count_pulses(x, hi, lo):
    count, armed = 0, True
    for v in x:
        if armed and v > hi:
            count, armed = count + 1, False
        elif not armed and v < lo:
            armed = True
    return count


def test_session_kinds_have_expected_shape(sessions):
    t = sessions["poke"]["time"]
    peak = SignalConfig().peak_flexion
    poke = sessions["poke"]["flexion"]
    assert poke[:, 1].max() > 0.7
    others = [k for k in range(5) if k != 1]
    assert np.all(poke[:, others] < 0.3)

    crush = sessions["crush"]["flexion"]
    late = t > 1.0
    assert np.all(crush[late].mean(axis=0) > 0.6)  # whole hand closed and held to the end
    onset = np.flatnonzero(crush[:, 1] > 0.3)[0]
    assert t[np.flatnonzero(crush[:, 1] > 0.9 * peak)[0]] - t[onset] < 0.4  # fast ramp

    rhr = sessions["ramp_hold_release"]["flexion"][:, 1]
    assert rhr[t < 0.3].max() < 0.2 and rhr[t > 2.8].max() < 0.2
    hold = (t > 1.3) & (t < 2.0)
    assert np.all(rhr[hold] > peak - 0.1)
    up = np.flatnonzero(rhr > 0.3)[0]
    assert 0.2 < t[np.flatnonzero(rhr > 0.9 * peak)[0]] - t[up] < 0.9  # ~0.8 s ramp

    pulses = sessions["pulses"]["flexion"]
    for k in range(4):
        assert _count_pulses(pulses[:, k], 0.6, 0.3) == 3
    assert _count_pulses(rhr, 0.6, 0.3) == 1


def test_fingertips_rest_outside_and_press_into_object(sessions, can_surface):
    s = sessions["ramp_hold_release"]
    r = np.linalg.norm(s["fingertip_positions"][..., :2], axis=-1)  # radial distance (can side)
    t = s["time"]
    rest = r[t < 0.3].mean(axis=0)
    np.testing.assert_allclose(rest, RADIUS + 0.005, atol=0.0015)  # ~5 mm standoff
    assert np.all(r[(t > 1.3) & (t < 2.0)].mean(axis=0) < RADIUS)  # pressed into the surface
    assert np.all(r.min(axis=0) > RADIUS - 0.25 * RADIUS - 0.002)  # at most the travel distance
    tips = s["fingertip_positions"][0]
    assert np.all(tips[1:, 0] > 0) and tips[0, 0] < 0  # thumb opposes the four fingers
    assert tips[1, 2] > tips[2, 2] > tips[3, 2] > tips[4, 2]  # index on top .. pinky at the bottom
    palm = s["palm_position"]
    assert np.all(palm[:, 1] < -RADIUS)  # palm on the -y side
    # palm frame z axis (third column of the rotation) points at the object (+y)
    w, x, y, z = s["palm_orientation"][0]
    zaxis = np.array([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)])
    assert zaxis[1] > 0.95


def test_synthesis_errors(can_surface):
    pts, nrm = can_surface
    with pytest.raises(SignalError, match="signal.session must be one of"):
        synthesize_session("wiggle", pts, nrm, SignalConfig())
    with pytest.raises(ValueError, match="signal.peak_flexion"):
        synthesize_session("poke", pts, nrm, SignalConfig(peak_flexion=1.5))
    with pytest.raises(SignalError, match="point into the object"):
        synthesize_session("poke", pts, -nrm, SignalConfig())


# ------------------------------------------------------------------------------------------------ CSV format
def test_csv_round_trip(tmp_path, sessions):
    s = sessions["crush"]
    path = write_recording(tmp_path / "sub" / "crush.csv", s)
    back = read_recording(path, frame_rate=30.0)
    assert set(back) == set(s)
    for k in s:
        np.testing.assert_allclose(back[k], s[k], rtol=1e-12, atol=1e-15, err_msg=k)
    np.testing.assert_array_equal(back["time"], s["time"])
    np.testing.assert_array_equal(back["flexion"], s["flexion"])


def test_percent_bent_scale_detection(tmp_path, sessions):
    s = sessions["pulses"]
    path = write_recording(tmp_path / "norm.csv", s)
    import pandas as pd

    df = pd.read_csv(path)
    flex_cols = [c for c in df.columns if c.startswith("flex_")]
    df[flex_cols] = np.round(df[flex_cols] * PERCENT_BENT_FULL_SCALE)
    df.to_csv(tmp_path / "pct.csv", index=False)
    back = read_recording(tmp_path / "pct.csv")
    np.testing.assert_allclose(back["flexion"], s["flexion"], atol=0.5 / PERCENT_BENT_FULL_SCALE + 1e-12)


def _write_table(path, rows, columns=REQUIRED_COLUMNS):
    lines = [",".join(columns)] + [",".join(str(v) for v in r) for r in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


def _good_rows(n=5, dt=0.01):
    rows = []
    for i in range(n):
        tips = [0.04, 0.0, 0.0] * 5
        rows.append([i * dt, 0.1, 0.2, 0.3, 0.4, 0.5] + tips + [0.0, -0.05, 0.0] + [1.0, 0.0, 0.0, 0.0])
    return rows


def test_extra_columns_order_spaces_and_quaternion_normalisation(tmp_path):
    cols = list(REQUIRED_COLUMNS)
    rows = _good_rows()
    for r in rows:
        r[-4:] = [2.0, 0.0, 0.0, 0.0]  # non-unit quaternion
    perm = cols[::-1] + ["frame_counter", "hand"]
    table = [[r[cols.index(c)] for c in cols[::-1]] + [i, "right"] for i, r in enumerate(rows)]
    path = tmp_path / "perm.csv"
    path.write_text(", ".join(perm) + "\n" + "\n".join(", ".join(str(v) for v in r) for r in table) + "\n")
    out = read_recording(path)
    np.testing.assert_allclose(out["flexion"][0], [0.1, 0.2, 0.3, 0.4, 0.5])
    np.testing.assert_allclose(out["palm_orientation"], np.tile([1.0, 0, 0, 0], (5, 1)))
    assert out["fingertip_positions"].shape == (5, 5, 3)


def _bad(tmp_path, name, mutate):
    rows = _good_rows()
    cols = list(REQUIRED_COLUMNS)
    rows, cols = mutate(rows, cols)
    return _write_table(tmp_path / name, rows, cols)


def _set(row, col, value):
    def mutate(rows, cols):
        rows[row][cols.index(col)] = value
        return rows, cols
    return mutate


def _drop_cols(*names):
    def mutate(rows, cols):
        keep = [i for i, c in enumerate(cols) if c not in names]
        return [[r[i] for i in keep] for r in rows], [cols[i] for i in keep]
    return mutate


CASES = [
    ("missing_cols.csv", _drop_cols("flex_ring", "palm_qz"), ["flex_ring", "palm_qz"]),
    ("non_numeric.csv", _set(2, "tip_index_y", "abc"), ["tip_index_y", "row 3", "'abc'"]),
    ("nan_cell.csv", _set(3, "palm_x", ""), ["palm_x", "row 4", "NaN"]),
    ("nan_text.csv", _set(1, "flex_middle", "nan"), ["flex_middle", "row 2"]),
    ("inf.csv", _set(1, "flex_thumb", "inf"), ["flex_thumb", "row 2", "inf"]),
    ("flex_range.csv", _set(2, "flex_pinky", 1.2), ["flex_pinky", "row 3", "is 1.2,", "1.05"]),
    ("flex_negative.csv", _set(0, "flex_index", -0.2), ["flex_index", "row 1"]),
    ("flex_pct_range.csv", lambda r, c: _set(1, "flex_ring", 12000)(*_set(0, "flex_thumb", 5000)(r, c)),
     ["flex_ring", "row 2", "percent-bent"]),
    ("dup_time.csv", _set(3, "time", 0.02), ["time 0.02 s is duplicated", "rows 3 and 4"]),
    ("backwards.csv", _set(4, "time", 0.005), ["backwards", "row 5"]),
    ("zero_quat.csv", lambda r, c: (_set(2, "palm_qw", 0.0)(r, c)), ["quaternion", "row 3"]),
    ("one_sample.csv", lambda r, c: (r[:1], c), ["1 sample"]),
    ("header_only.csv", lambda r, c: ([], c), ["0 sample"]),
    ("ragged.csv", lambda r, c: ([r[0], r[1] + [1, 2, 3], r[2]], c), ["not a readable CSV", "line 3"]),
]


@pytest.mark.parametrize("name, mutate, needles", CASES, ids=[c[0] for c in CASES])
def test_recording_validation_errors(tmp_path, name, mutate, needles):
    path = _bad(tmp_path, name, mutate)
    with pytest.raises(SignalError) as err:
        read_recording(path)
    msg = str(err.value)
    assert name in msg and "\n" not in msg, msg
    for needle in needles:
        assert needle in msg, (needle, msg)


def test_recording_file_level_errors(tmp_path):
    with pytest.raises(SignalError, match="does not exist") as err:
        read_recording(tmp_path / "nope.csv")
    assert "nope.csv" in str(err.value)
    empty = tmp_path / "empty.csv"
    empty.write_text("")
    with pytest.raises(SignalError, match="empty.csv.*empty"):
        read_recording(empty)
    blank = tmp_path / "blank.csv"
    blank.write_text("\n\n  \n")
    with pytest.raises(SignalError, match="blank.csv"):
        read_recording(blank)
    noheader = _write_table(tmp_path / "noheader.csv", _good_rows()[1:], [str(v) for v in _good_rows()[0]])
    with pytest.raises(SignalError, match="header row seems to be missing") as err:
        read_recording(noheader)
    assert "noheader.csv" in str(err.value)
    short = _write_table(tmp_path / "short.csv", _good_rows(3, dt=0.005))
    read_recording(short)  # fine without a frame rate
    with pytest.raises(SignalError, match="short.csv.*shorter than one frame"):
        read_recording(short, frame_rate=30.0)


def test_truncated_recording_names_the_cut_row(tmp_path):
    """An export or copy cut off mid-row (fewer fields in the last row, or half a number) is reported as a
    truncated file naming the row, not as a mysterious NaN or silently dropped."""
    head, last = _write_table(tmp_path / "full.csv", _good_rows(6)).read_text().rstrip("\n").rsplit("\n", 1)
    cut_fields = tmp_path / "cut_fields.csv"
    cut_fields.write_text(head + "\n" + ",".join(last.split(",")[:24]))  # last row: 24 of 28 fields
    cut_number = tmp_path / "cut_number.csv"
    cut_number.write_text(head + "\n0.05,0.1,1e-")  # cut in the middle of a number
    for path, fields in ((cut_fields, "24 of 28"), (cut_number, "3 of 28")):
        with pytest.raises(SignalError) as err:
            read_recording(path)
        msg = str(err.value)
        assert msg.startswith(f"recording {path}: the last row 6 (line 7) has {fields} fields") and "truncated" in msg
        assert "\n" not in msg
    # a NaN in the last row of a complete file is still a NaN (not called truncated)
    rows = _good_rows(6)
    rows[-1][3] = "nan"
    with pytest.raises(SignalError, match="column flex_middle row 6 .* is empty or NaN"):
        read_recording(_write_table(tmp_path / "nan_last.csv", rows))


def test_recording_above_the_size_limit_is_refused_unread(tmp_path):
    path = _write_table(tmp_path / "session.csv", _good_rows(50))
    size = path.stat().st_size
    assert len(read_recording(path, max_bytes=size)["time"]) == 50  # at the limit: read
    with pytest.raises(SignalError) as err:
        read_recording(path, max_bytes=size - 1)
    msg = str(err.value)
    assert msg.startswith(f"recording {path} is ") and "limit" in msg and "cut it to the squeeze" in msg
    assert len(read_recording(path, max_bytes=None)["time"]) == 50


def test_unit_and_scale_mistakes_are_refused_with_the_fix(tmp_path, sessions):
    """Percent 0..100 flexion, millisecond timestamps and mm or cm positions would each squeeze nothing (or run
    for hours): each is one line naming the file, what it looks like and the conversion to apply."""
    s = sessions["pulses"]
    percent = dict(s, flexion=s["flexion"] * 100)
    millis = dict(s, time=s["time"] * 1000)
    mm = dict(s, fingertip_positions=s["fingertip_positions"] * 1000, palm_position=s["palm_position"] * 1000)
    cm = dict(s, fingertip_positions=s["fingertip_positions"] * 100, palm_position=s["palm_position"] * 100)
    peak = float(np.max(s["flexion"]) * 100)
    reach = float(np.linalg.norm(mm["fingertip_positions"] - mm["palm_position"][:, None], axis=-1).max())
    step = float(np.median(np.diff(millis["time"])))
    for name, sig, line in (
        ("percent.csv", percent, f"flexion peaks at {peak:.4g}, which on SenseGlove's percent-bent scale 0..10000 is "
                                 f"{peak / 100:.2g} % bent (nothing would be squeezed); the flex_ columns look like "
                                 f"percent 0..100: divide them by 100 (0..1) or multiply them by 100 (0..10000)"),
        ("millis.csv", millis, f"time steps by {step:g} per sample (median; {millis['time'][-1] - millis['time'][0]:g} "
                               f"in all), a {1 / step:.3g} Hz sensor where SenseGlove streams at 100-1000 Hz; the "
                               f"time column looks like milliseconds: divide it by 1000 (seconds are expected)"),
        ("mm.csv", mm, f"fingertip positions reach {reach:.4g} m from the palm (a hand spans ~0.2 m); the CSV looks "
                       f"like millimetres: divide the tip_ and palm_x/y/z columns by 1000"),
        ("cm.csv", cm, f"fingertip positions reach {reach / 10:.4g} m from the palm (a hand spans ~0.2 m); the CSV "
                       f"looks like centimetres: divide the tip_ and palm_x/y/z columns by 100"),
    ):
        path = write_recording(tmp_path / name, sig)
        with pytest.raises(SignalError) as err:
            read_recording(path, frame_rate=30.0)
        assert str(err.value) == f"recording {path}: {line}"


def test_a_broken_tail_is_quoted_as_a_short_excerpt(tmp_path):
    """A recording whose tail is zero-filled (a crashed copy) or holds one huge garbage cell is reported with an
    excerpt of at most EXCERPT_CHARS characters, not echoed whole."""
    from tasks.core.excerpt import EXCERPT_CHARS

    good = _write_table(tmp_path / "good.csv", _good_rows(6)).read_bytes()
    zeros = tmp_path / "zeros.csv"
    zeros.write_bytes(good + b"\0" * 2_000_000)
    garbage = tmp_path / "garbage.csv"
    last = good.rstrip(b"\n").rsplit(b"\n", 1)[1].replace(b"0.05,", b"0.07,", 1)
    garbage.write_bytes(good + b"0.06," + b"x" * 2_000_000 + b"," * 26 + b"\n" + last + b"\n")
    for path in (zeros, garbage):
        with pytest.raises(SignalError) as err:
            read_recording(path)
        msg = str(err.value)
        assert msg.startswith(f"recording {path}") and "\n" not in msg
        assert len(msg) < len(str(path)) + 300 + 2 * EXCERPT_CHARS, msg[:400]
    assert "holds non-numeric 'xxxx" in msg and "... (2000000 characters)" in msg
