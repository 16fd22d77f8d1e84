"""Quasi-static damping of mass-scaled solids (``mpm.quasi_static_damping``, :class:`MPMSolver` class doc): a block
pushed by a constant force rings about its static compression without it and settles on the closed form with it."""
from __future__ import annotations

import numpy as np
import pytest

from tasks.physics.mpm import ForcePatch, Material, MPMSolver

DX = 0.01  # m
E = 1.0e4  # Pa
W, L = 4 * DX, 8 * DX  # m, block cross-section side and height
STRAIN = 0.02  # static strain the push gives: F = STRAIN E W^2


def _pushed_block(damping: float, frames: int = 30, frame_dt: float = 0.04):
    """A nu = 0 block on a sticky floor, density x4 (manual mass scaling), no gravity, its top face pushed down by
    F = STRAIN E W^2 from rest: returns (frame stats, top face displacement per frame in m, whether the quasi-static
    check passed the contact, judged when the run ends)."""
    h = DX / 2
    axes = [(np.arange(round(n / h)) + 0.5) * h for n in (W, W, L)]
    X = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    mat = Material(name="block", model="fixed_corotated", youngs_modulus=E, poisson_ratio=0.0, density=1000.0)
    s = MPMSolver(X, h ** 3, mat, config=dict(device="cpu", dx=DX, gravity=[0.0, 0.0, 0.0], floor_sticky=True,
                                              floor_height=0.0, mass_scaling="manual", mass_scale=4.0,
                                              quasi_static_damping=damping))
    top = X[:, 2] > L - h
    push = ForcePatch(X[top], np.zeros(int(top.sum()), int), np.array([[0.0, 0.0, -STRAIN * E * W * W]]))
    stats, drop = [], []
    for _ in range(frames):
        stats.append(s.step_frame(frame_dt, forces=push))
        drop.append(float(X[top, 2].mean() - s.positions()[top, 2].mean()))
    passed = s.close_quasi_static_contact()  # the run ends with the push on: its contact is judged now
    return stats, np.array(drop), passed


@pytest.mark.filterwarnings("ignore:quasi-static check")
@pytest.mark.parametrize("damping", [0.0, 0.8])
def test_force_driven_block_rings_undamped_and_settles_on_the_static_compression_damped(damping):
    """Closed form (nu = 0: uniaxial stress, no lateral coupling): the top face drops by STRAIN x L = 1.6 mm.  The
    block's lowest mode (fixed-free bar, period 4 L / c, c = sqrt(E / (4 rho)) = 1.58 m/s: 0.2 s = 5 frames) is
    excited by the suddenly applied force: undamped, the top oscillates between 0 and twice the static drop and the
    kinetic energy stays a third of the internal one (x = x_s (1 - cos wt): mean KE / mean IE = 1/3); with local damping 0.8 it settles
    on the static drop within a few periods and KE/IE over the contact stays below the check's 0.1."""
    stats, drop, passed = _pushed_block(damping)
    static = STRAIN * L
    ratio = stats[-1].ke_ie_contact
    if damping == 0.0:
        assert drop.max() > 1.6 * static  # dynamic overshoot of a step load (2x for an undamped oscillator)
        assert np.ptp(drop[-10:]) > 0.8 * static  # still ringing after 6 periods
        assert ratio > 0.2 and not passed
        assert all(st.local_damping == 0.0 for st in stats)
    else:
        assert abs(drop[-5:].mean() - static) < 0.1 * static, (drop[-5:], static)
        assert np.ptp(drop[-10:]) < 0.05 * static
        assert ratio < 0.1 and passed and all(st.quasi_static_ok for st in stats)
        assert all(st.local_damping == damping for st in stats)


def test_damping_coefficient_out_of_range_is_refused_in_one_line():
    from conf.mpm_schema import MPMConfigError, mpm_config_from

    for bad in (1.0, -0.1, float("nan")):
        with pytest.raises(MPMConfigError) as err:
            mpm_config_from(dict(quasi_static_damping=bad))
        assert str(err.value) == f"mpm.quasi_static_damping: must be in [0, 1) (0 = off; got {bad})"
