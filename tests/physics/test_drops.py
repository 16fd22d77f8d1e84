"""Drops fall at g, and the flight recorder only calls a sample free when its blob is (issue 50)."""
from __future__ import annotations

import numpy as np

from tasks.physics.free_flight import blob_flights, held_by_boundary, shares_node, stencil_bases
from tasks.physics.labels import INTERIOR
from tasks.physics.mpm import DirichletPoints, Material, MPMSolver
from tasks.physics.rollout_records import FlightRecord
from tests.physics.particles import lattice

DX = 0.005  # m
G = -9.81  # m/s^2
JUICE = Material(name="juice", model="fluid", bulk_modulus=2.0e5, viscosity=1e-3, density=1040.0)
PULP = Material(name="pulp", model="fixed_corotated", youngs_modulus=3.0e5, poisson_ratio=0.45, density=1040.0)


def _column(material: Material):
    X = lattice([0.0, 0.0, 0.0], [0.02, 0.02, 0.08], DX / 2)
    s = MPMSolver(X, (DX / 2) ** 3, material, config=dict(device="cpu", dx=DX, floor=False, margin_cells=4,
                                                       domain_lo=[-0.03, -0.03, -0.25], domain_hi=[0.05, 0.05, 0.2]))
    return s, X


def _accelerations(t: np.ndarray, z: np.ndarray, free: np.ndarray) -> np.ndarray:
    """Second differences (m/s^2) of the heights z (sample, particle) over three consecutive free samples."""
    h = np.diff(t)
    a = 2 * ((z[2:] - z[1:-1]) / h[1:, None] - (z[1:-1] - z[:-2]) / h[:-1, None]) / (h[1:] + h[:-1])[:, None]
    return a[free[:-2] & free[1:-1] & free[2:]]


def test_a_juice_column_falls_at_g_and_one_pushed_by_a_piston_is_not_free_fall():
    """An 8 cm column (2 x 2 cm, physical mass) in free space, sampled by the rollout's flight recorder every 2
    substeps for 40 ms:

    * juice (Tait fluid) dropped: one free blob; its centre of mass falls at g within 1 %, and every particle's free
      samples too (median within 2 %): pressure and viscosity are internal forces (measured -9.810 m/s^2);
    * torn pulp (elastic) pushed down from its top by a slip piston (grid-node points) accelerating at 2 g, as the
      crushed fruit pushes out what it releases: the column's lower part is more than two cells from the piston's
      nodes, so per particle 83 % of its samples looked free (the recorder before issue 50) and read 2 g (median
      -19.3 m/s^2: the piston's push carried down the column; so read the orange's +25-37 % 'free juice', every
      sample of which was in a jet still linked to the fruit); the recorder now holds every particle of a blob linked to the piston, so no sample
      is free and no flight is fitted.  (A juice column under the same piston does not carry the push: it splashes
      sideways under it and its foot keeps falling at g.)"""
    s, X = _column(JUICE)
    rec = FlightRecord.start(s, np.full(len(X), INTERIOR))
    rec.sample(s, 0.0)
    dt = 0.002
    for f in range(20):
        s.step_frame(dt, quasi_static=False, probe_every=2, probe=lambda t, f=f: rec.sample(s, f * dt + t))
        rec.sample(s, (f + 1) * dt)
    t, x, held = np.array(rec.times), np.array(rec.x, np.float64), np.array(rec.held)
    assert not held.any()
    (flight,) = blob_flights(t, x, held, s.lo, s.dx, rec.mass, rec.physical_mass, G)
    assert abs(flight.acceleration / G - 1.0) < 0.01, flight.acceleration
    assert abs(np.median(_accelerations(t, x[..., 2], ~held)) / G - 1.0) < 0.02

    s, X = _column(PULP)
    rec = FlightRecord.start(s, np.full(len(X), INTERIOR))
    top = X[X[:, 2] > X[:, 2].max() - 1e-9]
    state = {"t": 0.0}
    per_particle = []

    def piston(t, dt_sub):
        v = 2.0 * G * (state["t"] + t)  # m/s, accelerating at 2 g
        z = top[:, 2] + 0.5 * 2.0 * G * (state["t"] + t) ** 2
        return DirichletPoints(np.c_[top[:, :2], z], np.tile([0.0, 0.0, v], (len(top), 1)),
                               normals=np.tile([0.0, 0.0, 1.0], (len(top), 1)), advect=False)

    def sample(t):
        pts = piston(t, None).positions
        rec.sample(s, state["t"] + t, pts)
        b = stencil_bases(s.positions(), s.lo, s.dx)
        per_particle.append(shares_node(b, stencil_bases(pts, s.lo, s.dx))
                            | held_by_boundary(b, np.asarray(s.dims), int(s.cfg.padding), -np.inf))

    sample(0.0)
    for f in range(20):
        s.step_frame(dt, dirichlet=piston, quasi_static=False, probe_every=2, probe=sample)
        state["t"] += dt
        sample(0.0)
    t, x, held = np.array(rec.times), np.array(rec.x, np.float64), np.array(rec.held)
    looked_free = ~np.array(per_particle)
    a = _accelerations(t, x[..., 2], looked_free)
    assert looked_free.mean() > 0.3 and len(a) > 100
    assert np.median(a) / G > 1.3, np.median(a)  # carried by the piston's push, not falling at g
    assert held.all()
    assert not blob_flights(t, x, held, s.lo, s.dx, rec.mass, rec.physical_mass, G)
