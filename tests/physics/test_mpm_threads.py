"""``mpm.threads``: the fused G2P/P2G kernel split over CPU threads, the particles cut into chunks that each scatter
into their own grid (summed after every substep).  Known answers: the same run as on one thread up to float32 round-off
(positions, velocities, the colliders' reactions and the boundary work), with a released velocity field and surface
contact; reproducible; a guard tripped in a chunk other than the first is raised at its substep."""
from __future__ import annotations

import re
import warnings

import numpy as np
import pytest

from tasks.physics.mpm import Collider, Material, MPMSolver, SimulationError
from tasks.physics.mpm import launch as mpm_launch
from tests.physics.particles import lattice

DX = 0.005  # m
WALL = Material(name="wall", model="fixed_corotated", youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0)
BLOB = Material(name="blob", model="fluid", youngs_modulus=2e4, poisson_ratio=0.3, density=1000.0, viscosity=0.01,
                mass_scaled=False)


def squeeze(threads: int, frames: int = 4, contact: str = "surface"):
    """A soft block (5 x 4 x 4 cm, mass-scaled) on a plane collider (``contact``: ``grid``, the floor's grid nodes
    for the block, the plane for the blob), pressed by a descending capsule fingertip, and a fluid blob (released
    field) thrown at its side.  Returns the solver and the per-frame reactions (N)."""
    Xw = lattice([0.0, 0.0, 0.0], [0.05, 0.04, 0.04], DX / 2)
    Xb = lattice([0.06, 0.015, 0.015], [0.07, 0.025, 0.025], DX / 2)
    ids = np.repeat([0, 1], [len(Xw), len(Xb)])
    v = np.zeros((len(ids), 3), np.float32)
    v[ids == 1] = (-1.0, 0.0, 0.0)
    cfg = dict(device="cpu", dx=DX, mass_scaling="selective", target_substeps_per_frame=10, contact=contact,
               floor_height=0.0, gravity=[0.0, 0.0, -9.81], threads=threads, margin_cells=4)
    s = MPMSolver(np.concatenate([Xw, Xb]), (DX / 2) ** 3, [WALL, BLOB], material_ids=ids, velocities=v, config=cfg)
    reactions = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for f in range(frames):
            tip = Collider("sphere", (0.025, 0.02, 0.046 - 0.001 * f), radius=0.006, velocity=(0, 0, -0.06),
                           finger_id=1)
            st = s.step_frame(1.0 / 60.0, colliders=tip)
            reactions.append(np.r_[st.reaction.ravel(), st.boundary_work])
    return s, np.array(reactions)


def test_two_threads_share_the_released_fields_table_plane_under_grid_contact():
    """Grid contact: the table is a plane collider for the released field only (``Collider.field``); each thread's
    chunk sees it too: 1 and 2 threads agree to round-off (positions 1e-6 m, velocities 1e-4 m/s)."""
    one, _ = squeeze(1, frames=2, contact="grid")
    two, _ = squeeze(2, frames=2, contact="grid")
    assert two.threads == 2 and two.two_fields and two.table_plane_fields() == 1
    assert np.abs(two.positions() - one.positions()).max() < 1e-6
    assert np.abs(two.velocities() - one.velocities()).max() < 1e-4


@pytest.fixture(autouse=True)
def small_shares(monkeypatch):
    """Thread these small (fast) scenes too: the per-thread minimum is a speed threshold, not a limit."""
    monkeypatch.setattr(mpm_launch, "MIN_PARTICLES_PER_THREAD", 1024)


def test_two_threads_run_the_one_thread_squeeze_to_round_off():
    """Same scene on 1 and 2 threads (the chunks after the first hold block and blob particles, so both fields and
    the colliders go through their own grids and accumulators): positions agree to 1e-6 m (float32 round-off of
    the reordered sums; dx = 5 mm), velocities to 1e-4 m/s, the fingertip's and the floor's reactions and the
    boundary work to 1e-3 relative, and the fingertip does push (its reaction is not zero).  A second run on 2
    threads is bit for bit the first (whichever thread ran which chunk).  ``grid_nbytes`` counts the chunks' grids."""
    one, r1 = squeeze(1)
    two, r2 = squeeze(2)
    again, r3 = squeeze(2)
    assert np.array_equal(again.positions(), two.positions()) and np.array_equal(r3, r2)
    assert one.threads == 1 and two.threads == 2 and two.two_fields and len(two._ranges) == 4
    # memory: chunks 1-3 each hold one vec4 P2G buffer per velocity field
    assert two.grid_nbytes() == one.grid_nbytes() + 3 * 2 * 16 * int(np.prod(two.dims))
    ids = two.material_ids()
    assert ids[two._ranges[1][0]:].min() == 0 and ids[two._ranges[1][0]:].max() == 1
    assert np.abs(two.positions() - one.positions()).max() < 1e-6
    assert np.abs(two.velocities() - one.velocities()).max() < 1e-4
    assert np.abs(r1[-1, 5]) > 0  # the fingertip's vertical reaction (finger 1, z)
    assert np.allclose(r2, r1, rtol=1e-3, atol=1e-3 * np.abs(r1).max())


def test_a_guard_in_a_later_chunk_is_raised_at_its_substep():
    """The last particle (the last chunk) stretched to det F = 24 > ``j_max`` 20 (flags read every substep): the
    guard trips at substep 0, in the fused kernel's G2P of that chunk (the frame's last G2P, one launch with the
    main flags, would report a later substep), naming a particle beyond the first chunk (the stretched one's
    neighbours invert first)."""
    X = lattice([0.0, 0.0, 0.0], [0.04, 0.04, 0.04], DX / 2)
    s = MPMSolver(X, (DX / 2) ** 3, WALL, config=dict(device="cpu", dx=DX, threads=2, margin_cells=2,
                                                      check_every=1))
    F = np.tile(np.eye(3), (len(X), 1, 1))
    F[-1] *= 2.9
    s.set_deformation_gradients(F)
    assert s.threads == 2
    with pytest.raises(SimulationError, match="extreme volume change .* at substep 0 ") as err:
        s.step_frame(0.01)
    assert int(re.search(r"worst particle #(\d+)", str(err.value)).group(1)) >= s._ranges[1][0]
