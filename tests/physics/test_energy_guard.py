"""The energy guard knows every boundary's work and its tolerance has a floor from the loading's scale (issue 50):
a legitimate scripted squeeze runs clean from its first frame, a Courant-0.95 instability under the same kind of
loading still stops."""
from __future__ import annotations

import re

import numpy as np
import pytest

from tasks.physics.mpm import DirichletPoints, Material, MPMSolver, SimulationError
from tests.physics.particles import lattice

DX = 0.005  # m


def test_the_rubber_ball_squeezed_between_grid_node_plates_from_its_poles_runs_clean(tmp_path):
    """The default grid's hollow rubber ball as the ball study builds it (no gravity), the energy guard on at the
    pipeline's 0.25, squeezed between two grid-node plates (slip Dirichlet points, ``mpm.fingers=dirichlet``'s kind)
    that start at its poles and move 2 mm each on a ramped speed.  Before issue 50 the run stopped at frame 1:
    the scene preloaded a weightless body, whose thin wall reports ~1.7e-6 J of internal energy at rest, against a
    tolerance of 1e-9 J (0.25 x an energy scale of 0).  Now it runs clean: no preload without gravity, the plates'
    work credited from their impulses, and the tolerance never below the loading's force through one cell; the
    unexplained growth stays below 0.1 of the energy scale in every frame (measured <= 0.026)."""
    from flows.pipeline import evaluate_config, mpm_rollout_step, run_object_local, step_params
    from tasks.verification.ball import BALL_OVERRIDES, UNTIL, ball_scene
    from tasks.verification.contact import body_between_flats

    cfg = evaluate_config([*BALL_OVERRIDES, "mpm.energy_guard_tolerance=0.25"])
    refs = run_object_local(cfg, cfg.object, cfg.variant, str(tmp_path), until=UNTIL)
    scene = ball_scene(refs, step_params(mpm_rollout_step, cfg, cfg.object, cfg.variant))
    s = scene.solver
    assert scene.preload is None and s.cfg.energy_guard_tolerance == 0.25
    growth = []
    step = s.step_frame

    def recorded(*a, **k):
        st = step(*a, **k)
        growth.append(st.energy_growth)
        return st

    s.step_frame = recorded
    r = body_between_flats(s, "grid", 0.002, 20 * scene.frame_dt, 20)
    assert len(growth) == 20 and r["force"][-1] > 1.0  # the plates pressed the ball (N per plate)
    assert max(growth) < 0.1, growth


def test_a_courant_095_instability_under_a_pushing_plate_still_trips_the_guard():
    """The pre-compressed nu = 0.45 column of the unloaded Courant-0.95 case (tests/physics/test_mpm_guards.py), now pushed by a
    slip plate at 0.05 m/s: the plate's force raises the tolerance's floor (force x dx), but the instability grows
    the energy by orders of magnitude within a few substeps and the guard stops it with its one-line message; the
    same loading at Courant 0.3 runs 20 frames clean."""
    mat = Material(name="gel_column", model="fixed_corotated", youngs_modulus=4e6, poisson_ratio=0.45, density=1700.0)
    X = lattice([0, 0, 0], [4 * DX, 4 * DX, 8 * DX], DX / 2)
    bot = X[X[:, 2] < X[:, 2].min() + 1e-9]
    F0 = np.tile(np.diag([1.0, 1.0, 0.99]).astype(np.float32), (len(X), 1, 1))
    fdt = 5 * 0.95 * DX / mat.p_wave_speed()
    plate = DirichletPoints(bot, np.tile([0, 0, 0.05], (len(bot), 1)), normals=np.tile([0, 0, 1.0], (len(bot), 1)))
    for courant in (0.3, 0.95):
        s = MPMSolver(X, (DX / 2) ** 3, mat, config=dict(device="cpu", dx=DX, gravity=[0, 0, 0], floor=False,
                                                         courant=courant, courant_limit=1.0, margin_cells=12),
                      label="column")
        s.set_deformation_gradients(F0)
        if courant == 0.3:
            for _ in range(20):
                st = s.step_frame(fdt, dirichlet=plate)
            assert st.energy_growth < 0.25 and s._loading_force > 0
            continue
        with pytest.raises(SimulationError) as exc:
            for _ in range(20):
                s.step_frame(fdt, dirichlet=plate)
    msg = str(exc.value)
    assert re.match(r"object 'column': energy guard at frame \d+ \(t=.* s\)", msg) and "\n" not in msg, msg
    assert "Courant number 0.95" in msg
