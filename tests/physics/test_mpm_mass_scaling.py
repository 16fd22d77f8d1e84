"""The MLS-MPM acceleration knobs and selective mass scaling (real Warp kernels on the CPU): the mass scale and the
quasi-static bound in closed form, the lowest period of a slab, the kinetic-energy split, the quasi-static check, and
selective scaling that keeps weights physical (an unscaled blob falls at g beside a scaled solid; tracers follow at
any mass scale).
"""
from __future__ import annotations

import math
import re
import warnings

import numpy as np
import pytest

from conf.mpm_schema import MPMConfigError, mpm_config_from
from tasks.physics.mpm import (
    DirichletPoints,
    ForcePatch,
    Material,
    MPMSolver,
    mass_scale_for,
    material_mass_scales,
)
from tasks.physics.mpm.mass_scaling import QuasiStaticLoad, kinetic_energy_split, lowest_period, quasi_static_bound
from tests.physics.mpm_setup import DX, JELLY, cube, solver_for
from tests.physics.particles import lattice

pytestmark = pytest.mark.usefixtures("warm_mpm_kernels")


# ============================================================================================ acceleration knobs
def test_mass_scale_for_closed_form_and_fluids_do_not_drive_it():
    stiff = Material(name="stiff", model="fixed_corotated", youngs_modulus=1e8, poisson_ratio=0.3, density=1000.0)
    water = Material(name="water", model="fluid", density=1000.0, bulk_modulus=2.2e9)  # c = 1483 m/s > stiff's
    cfg = mpm_config_from({"mass_scaling": "auto", "target_substeps_per_frame": 20, "courant": 0.3})
    # s = (c_p (frame_dt / N) / (C dx))^2
    expected = (stiff.p_wave_speed() * (1 / 30 / 20) / (0.3 * DX)) ** 2
    assert mass_scale_for([stiff], DX, 1 / 30, cfg) == pytest.approx(expected, rel=1e-12)
    assert mass_scale_for([stiff, water], DX, 1 / 30, cfg) == mass_scale_for([stiff], DX, 1 / 30, cfg)
    assert mass_scale_for([water], DX, 1 / 30, cfg) == 1.0
    soft = mpm_config_from({"mass_scaling": "auto", "stiffness_scaling": 0.25,
                            "target_substeps_per_frame": 20})
    assert mass_scale_for([stiff], DX, 1 / 30, soft) == pytest.approx(expected / 4, rel=1e-12)
    relaxed = mpm_config_from({"mass_scaling": "auto", "target_substeps_per_frame": 1000})
    assert mass_scale_for([JELLY], DX, 1 / 30, relaxed) == 1.0  # needs ~180 substeps: s is never below 1
    assert mass_scale_for([stiff], DX, None, mpm_config_from({"mass_scaling": "off"})) == 1.0
    assert mass_scale_for([stiff], DX, None, mpm_config_from({"mass_scaling": "manual", "mass_scale": 7.0})) == 7.0


def test_quasi_static_bound_closed_form():
    """s <= (t_load / (k T1(1)))^2 with T1(1) = 4 H / sqrt(mu / rho) of the softest solid; s = max(1, min(s_cfl,
    s_qs)); off (inf) without a margin or a load; fluids do not set the period."""
    stiff = Material(name="stiff", model="fixed_corotated", youngs_modulus=1e8, poisson_ratio=0.3, density=1000.0)
    water = Material(name="water", model="fluid", density=1000.0, bulk_modulus=2.2e9)
    H, t_load, k = 0.05, 0.2, 2.0
    T1 = 4 * H / math.sqrt(JELLY.mu / JELLY.density)  # 0.0456 s: the jelly, 2000x softer, sets the slowest mode
    assert lowest_period([stiff, JELLY, water], H) == pytest.approx(T1, rel=1e-12)
    assert lowest_period([JELLY], H, mass_scale=9.0) == pytest.approx(3 * T1, rel=1e-12)  # T1(s) = sqrt(s) T1(1)
    assert lowest_period([water], H) == math.inf
    load = QuasiStaticLoad(rise_time=t_load, height=H)
    cfg = mpm_config_from({"mass_scaling": "global", "target_substeps_per_frame": 20, "quasi_static_margin": k})
    s_cfl = (stiff.p_wave_speed() * (1 / 30 / 20) / (0.3 * DX)) ** 2  # 3.2e4
    s_qs = (t_load / (k * T1)) ** 2  # 4.8
    assert quasi_static_bound([stiff, JELLY], cfg, load) == pytest.approx(s_qs, rel=1e-12)
    assert mass_scale_for([stiff, JELLY], DX, 1 / 30, cfg, load) == pytest.approx(s_qs, rel=1e-12)
    assert k * lowest_period([JELLY], H, mass_scale=s_qs) == pytest.approx(t_load, rel=1e-12)  # k T1(s) = t_load
    assert mass_scale_for([stiff, JELLY], DX, 1 / 30, cfg) == pytest.approx(s_cfl, rel=1e-12)  # no load: no bound
    off = mpm_config_from({"mass_scaling": "global", "target_substeps_per_frame": 20})
    assert quasi_static_bound([JELLY], off, load) == math.inf
    assert mass_scale_for([stiff, JELLY], DX, 1 / 30, off, load) == pytest.approx(s_cfl, rel=1e-12)
    fast = QuasiStaticLoad(rise_time=0.01, height=H)  # s_qs = 0.012 < 1: never below 1
    assert mass_scale_for([stiff, JELLY], DX, 1 / 30, cfg, fast) == 1.0
    slow = QuasiStaticLoad(rise_time=100.0, height=H)  # s_qs > s_cfl: the CFL target decides
    assert mass_scale_for([stiff, JELLY], DX, 1 / 30, cfg, slow) == pytest.approx(s_cfl, rel=1e-12)
    sel = mpm_config_from({"mass_scaling": "selective", "target_substeps_per_frame": 20, "quasi_static_margin": k})
    scales = material_mass_scales([stiff, JELLY, water], [stiff, JELLY, water], DX, 1 / 30, sel, load)
    # each scaled material: its own CFL factor (stiff 3.2e4, jelly 83) capped by its own bound (stiff: 2000x the
    # jelly's shear modulus, so 2000x its bound); water: 1; every material's scaled shear speed >= 4 H k / t_load
    np.testing.assert_allclose(scales, [2000 * s_qs, s_qs, 1.0], rtol=1e-12)
    speeds = [math.sqrt(m.mu / (m.density * x)) for m, x in zip([stiff, JELLY], scales)]
    assert min(speeds) == pytest.approx(4 * H * k / t_load, rel=1e-12)
    with pytest.raises(MPMConfigError, match=r"mpm.quasi_static_margin: must be a finite number >= 0 \(0 = off; "
                                             r"got -1.0\)"):
        mpm_config_from({"quasi_static_margin": -1.0})


def test_lowest_period_of_a_slab_on_a_sticky_floor_matches_4H_over_c_s():
    """The estimate T1 = 4 H / c_s is the shear fundamental of a layer held at its base (a quarter wave over H):
    a slab 3x wider than tall, held by the sticky floor, started in that mode (v_x ~ sin(pi z / 2H)), swings with
    the period :func:`lowest_period` gives, within 15 % (the sticky grid floor holds ~half a cell of the base)."""
    H, W = 0.04, 0.12
    X = lattice([0, 0, 0], [W, W / 4, H], DX / 2)
    V = np.zeros_like(X)
    V[:, 0] = 0.02 * np.sin(np.pi * X[:, 2] / (2 * H))
    s = solver_for(X, (DX / 2) ** 3, JELLY, velocities=V, gravity=[0, 0, 0], floor_sticky=True, margin_cells=4)
    T1 = lowest_period([JELLY], H)  # 0.036 s
    top = X[:, 2] > 0.75 * H
    t, u = [], []
    for _ in range(60):  # 2.5 periods, 24 frames per period
        s.step_frame(T1 / 24)
        t.append(s.time)
        u.append(s.positions()[top, 0].mean() - X[top, 0].mean())
    t, u = np.array(t), np.array(u) - np.mean(u)
    idx = np.flatnonzero(np.diff(np.sign(u)) != 0)
    tz = t[idx] - u[idx] * (t[idx + 1] - t[idx]) / (u[idx + 1] - u[idx])
    assert len(tz) >= 4
    T_meas = 2 * np.mean(np.diff(tz))
    assert abs(T_meas - T1) / T1 < 0.15, (T_meas, T1)


def test_kinetic_energy_split_separates_drift_rotation_and_deformation():
    """Koenig's theorem on a cubic lattice of 0.1 kg particles about (0.3, 0, 0.1) m (its inertia isotropic, so a
    symmetric strain rate carries no angular momentum): a drift v0 is all translation, 1/2 M |v0|^2, split across
    and along the vertical; a spin omega about the centre of mass is all rotation, 1/2 omega . I omega; a symmetric
    strain rate S r is all deformation, 1/2 sum m |S r|^2; their sum splits into the same parts.  A block squashed
    on the table (v_z = -a z from its base) moves its centre of mass vertically: 3/4 of its kinetic energy in the
    continuum limit (<z>^2 / <z^2>), 0.82 with 5 layers 1-5 cm above it, none horizontal.  Particles on a line spinning about
    a perpendicular axis: rotation 1/2 I omega^2, although the inertia tensor is singular about the line."""
    g = np.arange(-2, 3) * 0.01
    r = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    x, m = r + [0.3, 0.0, 0.1], np.full(len(r), 0.1)
    v0, omega = np.array([0.2, -0.1, 0.05]), np.array([1.0, 2.0, -3.0])
    S = np.array([[0.5, 0.2, 0.0], [0.2, -0.3, 0.1], [0.0, 0.1, 0.4]])
    inertia = m @ (r * r).sum(1) * np.eye(3) - np.einsum("i,ij,ik->jk", m, r, r)
    drift, spin, strain = np.tile(v0, (len(r), 1)), np.cross(omega, r), r @ S
    M = m.sum()
    known = (0.5 * M * (0.2 ** 2 + 0.1 ** 2), 0.5 * M * 0.05 ** 2, 0.5 * omega @ inertia @ omega,
             0.5 * m @ (strain ** 2).sum(1))
    assert np.allclose(kinetic_energy_split(x, drift, m), (*known[:2], 0, 0), rtol=1e-12, atol=1e-15)
    assert np.allclose(kinetic_energy_split(x, spin, m), (0, 0, known[2], 0), rtol=1e-12, atol=1e-15)
    assert np.allclose(kinetic_energy_split(x, strain, m), (0, 0, 0, known[3]), rtol=1e-12, atol=1e-15)
    assert np.allclose(kinetic_energy_split(x, drift + spin + strain, m), known, rtol=1e-12)
    h = x[:, 2] - x[:, 2].min() + 0.01  # 5 layers above a base at 0.01 m below the lowest one
    squash = np.c_[np.zeros((len(r), 2)), -h]
    parts = kinetic_energy_split(x, squash, m)
    assert parts[0] == pytest.approx(0, abs=1e-15) and parts[2] == pytest.approx(0, abs=1e-15)
    assert parts[1] / sum(parts) == pytest.approx(np.mean(h) ** 2 / np.mean(h ** 2), rel=1e-12)  # 0.82
    line = np.c_[g, np.zeros((5, 2))]
    w = np.array([0.0, 0.0, 2.0])  # about z, perpendicular to the line (along x)
    assert np.allclose(kinetic_energy_split(line, np.cross(w, line), np.ones(5)),
                       (0, 0, 0.5 * (g ** 2).sum() * 4.0, 0), atol=1e-15)


def _pushed_cube(margin: float, ramp: int = 3) -> tuple[list, list[str], list[dict]]:
    """A jelly cube (2 cm) on a sticky floor, left 3 frames under its weight, then pushed down on its top face by a
    force rising linearly to 1 N (5 % strain) in ``ramp`` frames of 1/30 s and then held for 12 - ``ramp`` frames,
    under global mass scaling at 10 substeps per frame
    (s = 330: the scaled cube's estimated slowest period 0.33 s, 10 frames) with ``mpm.quasi_static_margin``
    ``margin``; returns the frame statistics, the warning lines and the judged contacts (the run ends loaded)."""
    X, vol = cube(0.02)
    fdt = 1 / 30
    s = MPMSolver(X, vol, JELLY, config=dict(device="cpu", dx=DX, mass_scaling="global", target_substeps_per_frame=10,
                                             floor_sticky=True, quasi_static_margin=margin),
                  label="cube", load=QuasiStaticLoad(rise_time=ramp * fdt, height=0.02))
    top = X[X[:, 2] > X[:, 2].max() - 1e-9]
    fid = np.zeros(len(top), int)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        stats = [s.step_frame(fdt) for _ in range(3)]  # start-up under the weight, before the push
        for f in range(12):  # the force ramps within the frames too (a callable, evaluated every substep)
            stats.append(s.step_frame(fdt, forces=lambda t, dt, t0=f * fdt: ForcePatch(
                top, fid, np.array([[0.0, 0.0, -min((t0 + t) / (ramp * fdt), 1.0)]]))))
        s.close_quasi_static_contact()
    return stats, [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)], s.quasi_static_contacts


def test_force_driven_cube_is_quasi_static_with_the_bound_and_rings_without():
    """A mass-scaled body pushed faster than its period warns: the force rises within one frame (1/30 s) while the
    cube scaled for 10 substeps per frame swings with a period of ~10 frames, so it rings: the contact's KE/IE
    (sum KE / sum IE over its checked frames 6-15) 0.14 > 0.1, one line when the run ends still loaded.  (The 0.1 s
    ramp without the bound rings at 0.095, on the limit.)  With the bound on that ramp (k = 2: T1 <= t_load / 2)
    the mass scale drops to (t_load / (2 T1(1)))^2 = 7.5 and the cube follows its load: KE/IE < 0.001, no
    warning, at ~6.6x the substeps."""
    ringing, lines, contacts = _pushed_cube(0.0, ramp=1)
    assert ringing[0].mass_scale > 300 and len(lines) == 1 and "quasi-static check over frames 6-15" in lines[0]
    assert [(c["first_frame"], c["last_frame"]) for c in contacts] == [(6, 15)] and contacts[0]["ke_ie"] > 0.1
    assert contacts[0]["ke_ie"] == ringing[-1].ke_ie_contact  # the ratio of sums over the whole contact
    quiet, none, contacts = _pushed_cube(2.0)
    T1 = lowest_period([JELLY], 0.02)
    assert quiet[0].mass_scale == pytest.approx((0.1 / (2 * T1)) ** 2, rel=1e-9)
    assert none == [] and all(st.quasi_static_ok for st in quiet) and contacts[0]["ke_ie"] < 0.1
    cost = sum(st.substeps for st in quiet) / sum(st.substeps for st in ringing)
    assert cost == pytest.approx(math.sqrt(ringing[0].mass_scale / quiet[0].mass_scale), rel=0.1)


def test_mass_scaling_auto_caps_substeps_and_does_not_check_free_fall():
    stiff = Material(name="stiff", model="fixed_corotated", youngs_modulus=1e8, poisson_ratio=0.3, density=1000.0)
    X, vol = cube(0.02)
    s = solver_for(X, vol, stiff, mass_scaling="auto", target_substeps_per_frame=20, floor=False,
                   margin_cells=30)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # free fall: kinetic >> internal energy, but nothing to distort
        st = s.step_frame(1 / 30)
    assert st.ke_ie_ratio > 0.1 and not st.quasi_static_checked and st.quasi_static_ok
    assert st.substeps <= 20
    assert st.mass_scale == mass_scale_for([stiff], DX, 1 / 30, s.cfg) > 1.0
    assert s.c_max == pytest.approx(stiff.p_wave_speed() / math.sqrt(st.mass_scale))
    assert s.gravity == pytest.approx([0.0, 0.0, -9.81 / st.mass_scale])  # weight m g unchanged
    s2 = solver_for(X, vol, stiff, stiffness_scaling=0.01, gravity=[0, 0, 0])
    assert s2.c_max == pytest.approx(stiff.p_wave_speed() * 0.1)
    assert s2.step_frame(1 / 60).stiffness_scale == 0.01


def _plate_squeeze(speed: float, mass_scale: float, frames: int = 6, strain: float = 0.05):
    """A jelly cube on a sticky floor, left 3 frames under its weight (start-up), then pressed by a slip plate on its
    top face at ``speed`` m/s to ``strain`` in ``frames`` frames, with every density x ``mass_scale``, then one frame
    with the plate lifted (the contact ends); returns the frame statistics, the warning lines and the judged
    contacts."""
    X, vol = cube(0.02)
    s = MPMSolver(X, vol, JELLY, config=dict(device="cpu", dx=DX, mass_scaling="manual", mass_scale=mass_scale,
                                             floor_sticky=True), label="cube")
    top = X[X[:, 2] > X[:, 2].max() - 1e-9]
    plate = DirichletPoints(top, np.tile([0, 0, -speed], (len(top), 1)), normals=np.tile([0, 0, 1.0], (len(top), 1)))
    fdt = strain * 0.02 / speed / frames
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        stats = [s.step_frame(fdt) for _ in range(3)] + [s.step_frame(fdt, dirichlet=plate) for _ in range(frames)]
        stats.append(s.step_frame(fdt))
    return stats, [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)], s.quasi_static_contacts


def test_quasi_static_check_is_quiet_for_a_slow_squeeze_and_warns_for_a_dynamic_one():
    """KE/IE of a body pressed from rest to strain eps at speed v is about (v / c_s)^2 / (3 eps^2), c_s the wave
    speed after mass scaling: a 5 % squeeze at 0.01 m/s with s = 4 (c_s = 3.5 m/s) is quasi-static (KE/IE < 0.01 in
    the checked frames), the same squeeze 20x faster or with s = 1e4 (c_s = 0.07 m/s) is not (KE/IE > 0.5).  The
    start-up sag under the suddenly applied weight (KE/IE 0.8 in frame 1, as every default clay run showed), the
    contact's first two frames and the rebound after the plate lifts are never checked; the contact is judged when
    the plate lifts, and the dynamic runs warn once, in one line naming the object, the frames and times and the
    knobs."""
    slow, quiet, contacts = _plate_squeeze(0.01, 4.0)
    assert quiet == []
    assert slow[0].ke_ie_ratio > 0.5 and not slow[0].quasi_static_checked  # start-up: dynamic, not checked
    # + the contact's 2 first frames, and the rebound (KE/IE 30) once the plate is lifted
    assert [st.quasi_static_checked for st in slow] == [False] * 5 + [True] * 4 + [False]
    assert max(st.ke_ie_ratio for st in slow if st.quasi_static_checked) < 0.01 < slow[-1].ke_ie_ratio
    assert 0 < slow[8].ke_ie_contact < 0.01 and math.isnan(slow[4].ke_ie_contact)
    assert all(st.quasi_static_ok for st in slow)
    assert contacts == [{"first_frame": 6, "last_frame": 9, "ke_ie": slow[8].ke_ie_contact,
                         "sway_ke_share": contacts[0]["sway_ke_share"]}]
    assert contacts[0]["sway_ke_share"] < 0.01  # pressed straight down: its centre of mass moves vertically
    for speed, scale, shown in ((0.2, 4.0, "x4"), (0.01, 1e4, "x1e+04")):
        fast, lines, contacts = _plate_squeeze(speed, scale)
        assert len(lines) == 1, lines
        ratio = fast[8].ke_ie_contact  # sum KE / sum IE over the checked frames 6-9
        assert ratio == contacts[0]["ke_ie"] > 0.5
        assert [st.quasi_static_ok for st in fast] == [True] * 9 + [False]  # judged in the frame the plate lifts
        assert re.fullmatch(
            rf"object 'cube': quasi-static check over frames 6-9 of a contact \(t={fast[5].time:.4g}-"
            rf"{fast[8].time:.4g} s\): kinetic/internal energy ratio {ratio:.3g} of the mass-scaled material "
            rf"\('jelly' {re.escape(shown)}; {100 * contacts[0]['sway_ke_share']:.0f} % of its kinetic energy in the "
            r"body's sway on its base: horizontal motion of its centre of mass and rotation about it\) > "
            r"mpm.quasi_static_ke_ie_max=0.1 while the boundary loads it: the "
            r"squeeze is dynamic in the scaled time and inertia distorts the deformation; scale less "
            r"\(mpm.quasi_static_margin, now 0, bounds the scale by a force-driven load's rise time; "
            r"mpm.mass_scaling=off, or a larger mpm.target_substeps_per_frame\) or squeeze more slowly \(a longer "
            r"signal.duration\)", lines[0]), lines[0]


def test_quasi_static_check_judges_the_contact_not_its_first_frames():
    """Pressed at constant speed, KE is constant while IE grows like eps^2, so KE/IE falls like (n / f)^2 over the
    f-th of n loaded frames: at 0.06 m/s with s = 4 the first checked frame (eps = 2.5 %) reads 0.13 > 0.1, the end
    of the press (5 %) 0.036.  Judged as Abaqus/Explicit judges a quasi-static analysis (KE a small fraction of IE
    over the majority of the process), the contact's sum KE / sum IE is 0.06: no warning, where the running ratio
    of the contact's first frames alone (the former check) warned."""
    stats, lines, contacts = _plate_squeeze(0.06, 4.0)
    checked = [st for st in stats if st.quasi_static_checked]
    assert [st.frame for st in checked] == [6, 7, 8, 9]
    assert checked[0].ke_ie_ratio > 0.1 and checked[0].ke_ie_contact > 0.1  # the first checked frame alone
    assert checked[-1].ke_ie_ratio < 0.05
    assert lines == [] and len(contacts) == 1 and 0.03 < contacts[0]["ke_ie"] < 0.1
    assert contacts[0]["ke_ie"] == pytest.approx(sum(st.ke_ie_ratio * st.internal_energy for st in checked)
                                                 / sum(st.internal_energy for st in checked), rel=1e-6)


def test_quasi_static_check_skips_frames_declared_dynamic_and_unscaled_material():
    """Released material (``mass_scaled=False``, here a small block beside the pressed cube, falling, then thrown up
    at 1 m/s: real dynamics, its inertia is physical) does not enter the ratio, so a scene where only unscaled
    material moves does not warn; after a rupture the caller declares the frames dynamic (``quasi_static=False``):
    not checked, and the contact ends there."""
    X, vol = cube(0.02)
    X2 = lattice([0.03, 0, 0.03], [0.04, 0.01, 0.04], DX / 2)  # in the air beside the cube
    flying = Material(name="juice_like", model="fixed_corotated", youngs_modulus=5e4, poisson_ratio=0.3,
                      density=1000.0, mass_scaled=False)
    ids = np.r_[np.zeros(len(X), int), np.ones(len(X2), int)]
    s = MPMSolver(np.r_[X, X2], vol, [JELLY, flying], material_ids=ids, config=dict(
        device="cpu", dx=DX, mass_scaling="manual", mass_scale=4.0, floor_sticky=True, margin_cells=40), label="cube")
    top = X[X[:, 2] > X[:, 2].max() - 1e-9]
    plate = DirichletPoints(top, np.tile([0, 0, -0.01], (len(top), 1)), normals=np.tile([0, 0, 1.0], (len(top), 1)))
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        for bc in (None, None, None, plate, plate):  # start-up under the weight, then the slow press
            st = s.step_frame(1 / 60, dirichlet=bc)
        v = s.velocities()
        v[ids == 1] = [0.0, 0.0, 1.0]
        s.set_velocities(v)
        st = s.step_frame(1 / 60, dirichlet=plate)  # the jelly's ratio only: the flying block is not measured
        assert st.quasi_static_checked and st.quasi_static_ok and st.ke_ie_ratio < 0.1
        assert st.kinetic_energy / st.internal_energy > 1.0  # all materials: dominated by the flying block
        st = s.step_frame(1 / 60, dirichlet=plate, quasi_static=False)
        assert not st.quasi_static_checked and st.quasi_static_ok
    # the contact (frame 6) ended with the frame declared dynamic: judged on the jelly alone, no warning
    assert [(c["first_frame"], c["last_frame"]) for c in s.quasi_static_contacts] == [(6, 6)]
    assert s.quasi_static_contacts[0]["ke_ie"] < 0.1


def test_mass_scaling_keeps_weights_physical_and_only_slows_the_motion():
    """A column resting on a frictionless floor, dropped into gravity, with the densities x4 and gravity / 4.

    The momentum balance (4 rho) a = div sigma + (4 rho)(g / 4) has the solution x_4(t) = x(t / 2): the scaled run
    is the unscaled one, twice as slow, and every substep maps one to one (dt x 2); with s = 4 all the scalings
    are powers of two, so positions agree to float rounding (here bit for bit).  Hence the same static
    compression: the centroid drop averaged over whole oscillation periods (T = 4 H / sqrt(E / rho) = 0.05 s,
    5 frames) matches the uniaxial closed form rho g H^2 / (3 E) within 10 % in both runs (the MPM column, 16
    particles tall, gives 0.94 of it); without the gravity compensation it would be 4 x larger.
    """
    E, rho, H, W = 1e4, 1000.0, 0.04, 0.02
    mat = Material(name="block", model="fixed_corotated", youngs_modulus=E, poisson_ratio=0.3, density=rho)
    X = lattice([0, 0, 0], [W, W, H], DX / 2)
    closed = rho * 9.81 * H ** 2 / (3 * E)  # m, centroid drop of a laterally free column under its own weight
    runs = {}
    for s_mass in (1.0, 4.0):
        s = solver_for(X, (DX / 2) ** 3, mat, mass_scaling="manual" if s_mass > 1 else "off", mass_scale=s_mass)
        assert s.gravity == pytest.approx([0.0, 0.0, -9.81 / s_mass])
        xs = []
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # the drop oscillates: KE/IE > 0.1 is expected
            for _ in range(20):
                s.step_frame(0.01 * math.sqrt(s_mass))
                xs.append(s.positions())
        runs[s_mass] = np.array(xs)
        drop = X[:, 2].mean() - runs[s_mass][..., 2].mean(axis=1)  # (frame,)
        assert drop.mean() == pytest.approx(closed, rel=0.1), (s_mass, drop.mean() / closed)
    np.testing.assert_allclose(runs[4.0], runs[1.0], rtol=0, atol=1e-7)


# ============================================================================================ selective mass scaling
def _fit_acceleration(t: np.ndarray, z: np.ndarray) -> float:
    """Second derivative (m/s^2) of the least-squares parabola z(t) = c0 + c1 t + c2 t^2 through the samples."""
    return 2.0 * float(np.polyfit(t, z, 2)[0])


def test_selective_mass_scaling_unscaled_blob_falls_at_g_next_to_a_scaled_solid():
    """Two cubes 2 cm apart fall freely (no floor, no contact): a stiff solid (E 1 MPa, scaled by s) and a soft blob
    with ``mass_scaled=False``.  Known answers: weights stay physical, so the scaled solid accelerates at g / s and
    the blob at g (fitted from the centroid trajectories, within 5 %; under global scaling the blob would also fall
    at g / s); the total momentum grows as t g sum m_phys (1 %); the blob's kinetic energy equals the potential
    energy it released, m g |dz| (2 %); the stable step is the smaller of the two materials' own steps."""
    solid = Material(name="solid", model="fixed_corotated", youngs_modulus=1e6, poisson_ratio=0.3, density=1000.0)
    blob = Material(name="blob", model="fixed_corotated", youngs_modulus=2e4, poisson_ratio=0.3, density=1000.0,
                    mass_scaled=False)
    Xa, vol = cube(0.01)
    Xb = Xa + [0.03, 0.0, 0.0]
    X = np.concatenate([Xa, Xb])
    ids = np.repeat([0, 1], len(Xa))
    frame_dt, frames = 1 / 60, 12
    runs = {}
    for mode in ("selective", "global"):
        s = solver_for(X, vol, [solid, blob], material_ids=ids, mass_scaling=mode, target_substeps_per_frame=20,
                       floor=False, domain_lo=[-0.02, -0.02, -0.25], domain_hi=[0.06, 0.03, 0.03])
        zs, pz = [s.positions()[:, 2]], [0.0]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # free fall is all kinetic energy
            for _ in range(frames):
                st = s.step_frame(frame_dt)
                zs.append(s.positions()[:, 2])
                pz.append(float(st.momentum[2]))
        runs[mode] = (s, np.array(zs), np.array(pz), st)
    s, zs, pz, st = runs["selective"]
    scale = s.mass_scale
    assert scale == pytest.approx(mass_scale_for([solid], DX, frame_dt, s.cfg)) and scale > 50
    np.testing.assert_allclose(s.material_mass_scale, [scale, 1.0])
    t = frame_dt * np.arange(frames + 1)
    a_solid = _fit_acceleration(t, zs[:, ids == 0].mean(axis=1))
    a_blob = _fit_acceleration(t, zs[:, ids == 1].mean(axis=1))
    assert a_blob == pytest.approx(-9.81, rel=0.05)
    assert a_solid == pytest.approx(-9.81 / scale, rel=0.05)
    m_phys = s.physical_masses()
    np.testing.assert_allclose(s.masses(), m_phys * np.where(ids == 0, scale, 1.0), rtol=1e-6)
    np.testing.assert_allclose(pz, -9.81 * t * m_phys.sum(), rtol=0.01)
    drop = zs[0, ids == 1].mean() - zs[-1, ids == 1].mean()
    ke_blob = 0.5 * (m_phys[ids == 1] * np.sum(s.velocities()[ids == 1] ** 2, axis=1)).sum()
    assert ke_blob == pytest.approx(m_phys[ids == 1].sum() * 9.81 * drop, rel=0.02)
    dts = s.stable_dt_per_material()
    assert dts["blob"] == pytest.approx(0.3 * DX / blob.p_wave_speed(), rel=1e-6)
    assert dts["solid"] == pytest.approx(0.3 * DX / solid.p_wave_speed(mass_scale=scale), rel=1e-6)
    assert st.dt_max <= min(dts.values()) * (1 + 1e-6)
    g_s, zg, _, _ = runs["global"]
    assert _fit_acceleration(t, zg[:, ids == 1].mean(axis=1)) == pytest.approx(-9.81 / g_s.mass_scale, rel=0.05)


def test_selective_mass_scaling_keeps_the_static_compression_of_a_scaled_column():
    """The resting column of the test above (rho g H^2 / (3 E), the MPM column gives 0.94 of it) under selective
    scaling with an unscaled soft block resting elsewhere on the floor: the weight goes through the P2G impulse
    dt m_phys g instead of the grid's g / s, and the column's trajectory is the global-scaling one to float rounding
    (1e-6 m), its mean drop within 10 % of the closed form."""
    E, rho, H, W = 1e4, 1000.0, 0.04, 0.02
    mat = Material(name="block", model="fixed_corotated", youngs_modulus=E, poisson_ratio=0.3, density=rho)
    soft = Material(name="soft", model="fixed_corotated", youngs_modulus=500.0, poisson_ratio=0.3, density=rho,
                    mass_scaled=False)
    Xc = lattice([0, 0, 0], [W, W, H], DX / 2)
    Xs = lattice([0.05, 0, 0], [0.06, 0.01, 0.01], DX / 2)
    X = np.concatenate([Xc, Xs])
    ids = np.repeat([0, 1], [len(Xc), len(Xs)])
    closed = rho * 9.81 * H ** 2 / (3 * E)
    runs = {}
    for mode in ("selective", "global"):
        s = solver_for(X, (DX / 2) ** 3, [mat, soft], material_ids=ids, mass_scaling=mode,
                       target_substeps_per_frame=12)
        xs = []
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            for _ in range(40):
                s.step_frame(0.02)
                xs.append(s.positions()[ids == 0])
        runs[mode] = (s, np.array(xs))
    s, xs = runs["selective"]
    assert s._weight_in_p2g and not runs["global"][0]._weight_in_p2g
    assert s.mass_scale == pytest.approx(runs["global"][0].mass_scale) and s.mass_scale > 4
    drop = Xc[:, 2].mean() - xs[..., 2].mean(axis=1)
    assert drop.mean() == pytest.approx(0.94 * closed, rel=0.1), drop.mean() / closed
    np.testing.assert_allclose(xs, runs["global"][1], rtol=0, atol=1e-6)


def test_mass_scaling_modes_and_per_material_scales():
    """``selective`` scales only ``Material.is_mass_scaled`` materials (every model but fluids by default);
    ``global`` (former ``auto``) and ``manual`` scale all; a bad mode is refused with the known list."""
    stiff = Material(name="stiff", model="fixed_corotated", youngs_modulus=1e8, poisson_ratio=0.3, density=1000.0)
    juice = Material(name="juice", model="fluid", density=1000.0, bulk_modulus=1e5)
    loose = Material(name="loose", model="foam", youngs_modulus=1e4, density=100.0, yield_stress=10.0,
                     mass_scaled=False)
    assert stiff.is_mass_scaled and not juice.is_mass_scaled and not loose.is_mass_scaled
    assert Material(model="fluid", mass_scaled=True).is_mass_scaled
    assert mpm_config_from({"mass_scaling": "auto"}).mass_scaling == "global"
    with pytest.raises(MPMConfigError, match="'bogus' is not one of selective, global, manual, off"):
        mpm_config_from({"mass_scaling": "bogus"})
    X, vol = cube(0.02)
    ids = np.arange(len(X)) % 3
    for mode, expect in (("selective", [1, 0, 0]), ("global", [1, 1, 1])):
        s = solver_for(X, vol, [stiff, juice, loose], material_ids=ids, mass_scaling=mode,
                       target_substeps_per_frame=20, gravity=[0, 0, 0])
        s.step_frame(1 / 30)
        np.testing.assert_allclose(s.material_mass_scale, np.where(expect, s.mass_scale, 1.0))
        assert s.mass_scale == pytest.approx(mass_scale_for([stiff], DX, 1 / 30, s.cfg))


def test_embedded_tracers_reproduce_an_affine_motion_exactly_and_ignore_non_anchor_particles():
    """Tracers are embedded in their nearest anchor particles: after the particles are moved by x = A X + b with
    F = A (set directly, no stepping), every tracer sits at A X_t + b and carries F = A (to float32 precision),
    including tracers dx/4 outside the cube; a second cube that is not an anchor moves elsewhere and pulls none."""
    X, vol = cube(0.02)
    other = X + [0.05, 0.0, 0.0]
    rng = np.random.default_rng(3)
    tr = X[rng.choice(len(X), 40, replace=False)] + 0.25 * DX * rng.standard_normal((40, 3))
    s = MPMSolver(np.r_[X, other], vol, JELLY, config=dict(device="cpu", dx=DX, floor=False, gravity=[0, 0, 0]),
                  tracers=tr, tracer_anchors=np.r_[np.ones(len(X), bool), np.zeros(len(other), bool)])
    A = np.array([[1.1, 0.2, 0.0], [-0.1, 0.9, 0.05], [0.0, 0.1, 1.2]])
    b = np.array([0.003, -0.002, 0.004])
    moved_other = other + [0.0, 0.0, 0.01]
    s.set_positions(np.r_[X @ A.T + b, moved_other])
    s.set_deformation_gradients(np.r_[np.tile(A, (len(X), 1, 1)), np.tile(np.eye(3), (len(other), 1, 1))])
    np.testing.assert_allclose(s.tracer_positions(), tr @ A.T + b, atol=1e-6)
    np.testing.assert_allclose(s.tracer_state()[1], np.tile(A, (len(tr), 1, 1)), atol=1e-6)


def test_surface_tracers_move_with_a_translating_body_at_any_mass_scale():
    """Tracers on the faces of a cube (dx/4 outside its outermost particles, as surface Gaussians lie) and at its
    corners, the cube translating at 0.2 m/s through gravity (no floor): every tracer's displacement equals the
    cube's centroid displacement within 1 % of dx, with the interpolation renormalised over the nodes that carry
    mass (the empty nodes of a tracer's stencil would otherwise pull it back), at mass scales 1 and 1e4."""
    X, vol = cube(0.02)
    lo, hi = X.min(axis=0) - DX / 4, X.max(axis=0) + DX / 4
    g = np.linspace(0, 1, 5)
    face = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    tr = []
    for axis in range(3):
        other = [a for a in range(3) if a != axis]
        for side in (lo, hi):
            p = np.empty((len(face), 3))
            p[:, axis] = side[axis]
            p[:, other] = lo[other] + face * (hi - lo)[other]
            tr.append(p)
    tr = np.concatenate(tr)
    v0 = np.array([0.2, -0.1, 0.05])
    for mode, scale in (("off", 1.0), ("manual", 1.0e4)):
        s = solver_for(X, vol, JELLY, velocities=np.tile(v0, (len(X), 1)), tracers=tr, floor=False,
                       margin_cells=12, mass_scaling=mode, mass_scale=scale)
        c0 = s.positions().mean(axis=0)
        for _ in range(6):
            s.step_frame(1 / 60)
        moved = s.positions().mean(axis=0) - c0
        assert np.linalg.norm(moved) > 4 * DX
        err = np.abs(s.tracer_positions() - tr - moved).max()
        assert err < 0.01 * DX, (mode, err / DX)
