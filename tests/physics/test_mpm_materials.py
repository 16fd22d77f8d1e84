"""MLS-MPM materials, configuration and devices (real Warp kernels on the CPU): material validation and wave
speeds, the device choice, CPU and CUDA agreement, a material switch's time step, and a fluid column that settles
keeping its volume.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import warp as wp

from conf.mpm_schema import MPMConfigError, mpm_config_from
from tasks.physics.mpm import (
    Material,
    MaterialError,
    MPMSolver,
)
from tests.physics.mpm_setup import DX, JELLY, cube, solver_for
from tests.physics.particles import lattice

pytestmark = pytest.mark.usefixtures("warm_mpm_kernels")


# ============================================================================================ materials / config
def test_material_validation_and_wave_speed():
    with pytest.raises(MaterialError, match="poisson_ratio 0.5 makes lambda infinite; use <= 0.49"):
        Material(model="elastic", poisson_ratio=0.5)
    for bad in (dict(youngs_modulus=0.0), dict(youngs_modulus=-1.0), dict(density=0.0), dict(poisson_ratio=-0.1)):
        with pytest.raises(MaterialError):
            Material(**bad)
    with pytest.raises(MaterialError, match="yield_stress"):
        Material(model="metal")
    with pytest.raises(MaterialError, match="cohesion must be >= 0"):
        Material(cohesion=-1.0, mass_scaled=False)
    with pytest.raises(MaterialError, match="give it mass_scaled=False"):  # the body's own field has no such contact
        Material(cohesion=100.0)
    m = Material(youngs_modulus=1e6, poisson_ratio=0.3, density=1000.0)
    E, nu, rho = 1e6, 0.3, 1000.0
    assert m.p_wave_speed() == pytest.approx(math.sqrt(E * (1 - nu) / (rho * (1 + nu) * (1 - 2 * nu))))
    assert m.p_wave_speed() == pytest.approx(math.sqrt((m.lam + 2 * m.mu) / rho))
    assert m.p_wave_speed(mass_scale=4.0) == pytest.approx(m.p_wave_speed() / 2)
    assert m.p_wave_speed(stiffness_scale=4.0) == pytest.approx(m.p_wave_speed() * 2)
    assert Material(model="water", bulk_modulus=2e5).p_wave_speed() == pytest.approx(math.sqrt(2e5 / 1000.0))
    cfg = mpm_config_from(dict(courant=0.4))
    assert cfg.device == "auto" and cfg.courant == 0.4
    with pytest.raises(MPMConfigError, match="unknown"):
        mpm_config_from(dict(courant_number=0.4))
    with pytest.raises(MPMConfigError, match="courant"):
        mpm_config_from(dict(courant=1.5))
    # measured unstable without any guard firing (flows.stability): refused unless the user raises the limit
    with pytest.raises(MPMConfigError, match=r"mpm.courant: must be in \(0, courant_limit=0.8\] \(got 0.95\)"):
        mpm_config_from(dict(courant=0.95))
    assert mpm_config_from(dict(courant=0.95, courant_limit=1.0)).courant == 0.95


def test_device_auto_selects_available():
    X, vol = cube(0.01)
    s = MPMSolver(X, vol, JELLY, config=dict(dx=DX))
    assert s.device == ("cuda:0" if wp.get_cuda_device_count() > 0 else "cpu")


# ============================================================================================ devices
@pytest.mark.skipif(wp.get_cuda_device_count() == 0, reason="no CUDA device")
def test_cpu_and_cuda_agree():
    X, vol = cube(0.02)
    out = []
    for dev in ("cpu", "cuda:0"):
        s = solver_for(X, vol, JELLY, device=dev)
        for _ in range(3):
            s.step_frame(1 / 60)
        out.append(s.positions())
    assert np.abs(out[0] - out[1]).max() < 1e-3 * DX


def test_material_switch_updates_the_time_step_and_leaves_the_fixed_corotated_fast_path():
    """A rupture re-labels particles mid-run: the stable step must follow the new wave speed (substeps scale with
    c_p, 10x for 100x E at equal density) and a non-corotated model must leave the all-corotated kernel."""
    X, vol = cube(0.02)
    s = solver_for(X, vol, [JELLY, Material(name="stiff_gel", model="neo_hookean", youngs_modulus=5e6,
                                            poisson_ratio=0.3, density=1000.0)], gravity=[0, 0, 0], floor=False)
    assert s.all_corotated
    before = s.step_frame(1 / 60).substeps
    s.set_material_ids(np.ones(s.n_particles, np.int32))
    assert not s.all_corotated
    after = s.step_frame(1 / 60).substeps
    assert after == pytest.approx(10 * before, rel=0.05)
    assert np.isfinite(s.positions()).all()


# ============================================================================================ fluid
def test_fluid_column_settles_and_keeps_volume():
    juice = Material(name="juice", model="fluid", density=1000.0, bulk_modulus=1e5, viscosity=1e-2)
    X = lattice([0, 0, 0], [0.05, 0.02, 0.06], DX / 2)
    s = solver_for(X, (DX / 2) ** 3, juice, domain_lo=[0.0, 0.0, 0.0], domain_hi=[0.12, 0.02, 0.08],
                   floor_friction=0.0)
    V0 = len(X) * (DX / 2) ** 3
    kes = []
    for _ in range(12):
        st = s.step_frame(1 / 30)
        kes.append(st.kinetic_energy)
        J = np.linalg.det(s.deformation_gradients().astype(np.float64))
        assert abs(J.sum() * (DX / 2) ** 3 - V0) / V0 < 0.03  # weakly compressible: volume within 3 %
    x = s.positions()
    assert x[:, 2].max() < 0.06 - 0.01  # the column collapsed
    assert x[:, 0].max() > 0.08  # and spread along the box
    assert kes[-1] < 0.5 * max(kes)  # and is settling
    F = s.deformation_gradients()
    off = F - np.eye(3) * np.cbrt(np.linalg.det(F))[:, None, None]
    assert np.abs(off).max() < 1e-5  # F_E = J^(1/3) I
