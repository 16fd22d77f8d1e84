"""The released material's free flight (tasks.physics.free_flight): free blobs, their flights and g (known
answers from synthetic trajectories whose contacts are known)."""
from __future__ import annotations

import numpy as np
import pytest

from tasks.physics.free_flight import (
    blob_flights,
    coupled_components,
    flight_summary,
    held_by_boundary,
    prune_held,
    shares_node,
    stencil_bases,
)

G = -9.81
DX = 0.004
ORIGIN = np.array([-0.1, -0.1, -0.02])  # the table z = 0 is node 5
DIMS = np.array([50, 50, 80])
FLOOR_NODE = 5.0


def _held(x: np.ndarray, body: np.ndarray) -> np.ndarray:
    bases = stencil_bases(x, ORIGIN, DX)
    return shares_node(bases, stencil_bases(body, ORIGIN, DX)) | held_by_boundary(bases, DIMS, 3, FLOOR_NODE)


def test_stencils_share_a_node_exactly_when_their_bases_are_at_most_two_apart():
    """Quadratic B-splines (3 nodes per axis from floor(g - 0.5)): particles 2.9 dx apart share a node or not
    depending on where they sit in their cells (checked against the node sets), 1.9 dx apart they do, 3.1 dx not."""
    a = np.array([[0.0, 0.0, 0.0]])
    for gap, sits, shares in [(2.9, 0.55, True), (2.9, 0.95, False), (1.9, 0.55, True), (3.1, 0.55, False)]:
        x = (np.array([[sits, sits, sits]]) + np.array([[0.0, 0.0, 0.0], [gap, 0.0, 0.0]])) * DX + ORIGIN
        b = stencil_bases(x, ORIGIN, DX)
        nodes = [{tuple(bb + np.array(o)) for o in np.ndindex(3, 3, 3)} for bb in b]
        assert bool(nodes[0] & nodes[1]) == shares == bool(shares_node(b[1:], b[:1])[0])
        assert (len(set(coupled_components(b))) == 1) == shares
    assert not shares_node(stencil_bases(a, ORIGIN, DX), np.zeros((0, 3), int)).any()


def test_flights_exclude_contact_and_recover_g_from_the_centre_of_mass():
    """Synthetic record, 1 ms samples over 0.12 s, beside a body (a vertical post of particles at x = y = 0) and on a
    table (z = 0):
    * a 2x2x2 blob flies past the post at 1 m/s; while it passes (|x| < 6 mm, inside the 10 mm the post's stencils
      reach) the post holds it up (its vertical acceleration is 0): one flight before and one after the contact,
      none containing a contact sample, both at g (exact parabolas);
    * a pair of particles vibrating against each other (internal force: each particle's height is far from a
      parabola) whose centre of mass falls at g: one flight over the whole record, at g; a per-particle fit is not;
    * a jet standing on the table, 6 cm tall, linked node to node: its top particles are far from the table and
      the post but none of them flies free; left out of the record where held throughout (its foot), the flights
      are the same.
    Leaving the contact in (nothing held) biases the fit by > 5 %: the exclusion is what recovers g."""
    t = np.arange(121) * 1e-3
    post = np.stack(np.broadcast_arrays(0.0, 0.0, np.arange(0.0, 0.3, DX / 2)), -1)
    # the passing blob: centre x = -0.06 + t, z integrated with a = g outside the contact and 0 inside it
    xc = -0.06 + 1.0 * t
    touching = np.abs(xc) < 0.006
    vz, zc = np.empty_like(t), np.empty_like(t)
    vz[0], zc[0] = 0.3, 0.15
    for s in range(1, len(t)):
        a = 0.0 if touching[s - 1] else G
        zc[s] = zc[s - 1] + vz[s - 1] * 1e-3 + 0.5 * a * 1e-6
        vz[s] = vz[s - 1] + a * 1e-3
    cube = (np.stack(np.meshgrid(*[[-1e-3, 1e-3]] * 3, indexing="ij"), -1).reshape(-1, 3))
    blob = cube[None] + np.stack([xc, np.zeros_like(t), zc], -1)[:, None]
    # the vibrating pair at x = 0.05, y = 0.05: centre of mass z = 0.2 + 0.5 t + g t^2 / 2
    com = 0.2 + 0.5 * t + 0.5 * G * t ** 2
    wobble = 1.5e-3 * np.sin(2 * np.pi * t / 0.05)
    pair = np.stack([np.stack(np.broadcast_arrays(0.05, 0.05, com + wobble + 1e-3), -1),
                     np.stack(np.broadcast_arrays(0.05, 0.05, com - wobble - 1e-3), -1)], 1)
    # the jet at x = -0.05, y = 0.05, from the table up
    jet = np.broadcast_to(np.stack(np.broadcast_arrays(-0.05, 0.05, np.arange(0.001, 0.06, DX / 2)), -1),
                          (len(t), 30, 3))
    x = np.concatenate([blob, pair, jet], axis=1)
    held = np.stack([_held(xs, post) for xs in x])
    n = x.shape[1]
    mass = np.full(n, 1e-6)
    assert held[touching][:, :8].any(axis=1).all()  # the contact the synthetic force acts in is detected

    flights = blob_flights(t, x, held, ORIGIN, DX, mass, mass)
    of_blob = sorted([fl for fl in flights if set(fl.members) <= set(range(8))], key=lambda fl: fl.start)
    assert len(of_blob) == 2 and all(len(fl.members) == 8 for fl in of_blob)
    contact = np.flatnonzero(touching)
    assert of_blob[0].stop <= contact[0] and of_blob[1].start > contact[-1]
    assert of_blob[0].stop - of_blob[0].start > 30 and of_blob[1].stop - of_blob[1].start > 30
    (of_pair,) = [fl for fl in flights if set(fl.members) & {8, 9}]
    assert set(of_pair.members) == {8, 9} and (of_pair.start, of_pair.stop) == (0, len(t))
    assert not any(set(fl.members) & set(range(10, n)) for fl in flights)  # the jet never flies free
    for fl in flights:
        assert fl.acceleration == pytest.approx(G, rel=1e-6) and fl.expected == G
    each = [2 * np.polyfit(t, x[:, p, 2], 2)[0] for p in (8, 9)]
    assert min(abs(a / G - 1) for a in each) > 0.07  # one particle's height is no free fall: the pair's is
    summary = flight_summary(flights)
    assert summary["acceleration"] == pytest.approx(G, rel=1e-6) and summary["error"] == pytest.approx(0, abs=1e-6)
    assert summary["flights"] == 3 and summary["particles"] == 10
    assert summary["longest_flight"] == pytest.approx(0.12)
    # the record pruned of the particles held throughout (the jet's foot) has the same flights
    kept, near = prune_held(x, held, ORIGIN, DX)
    assert 0 < (~kept).sum() < 30 and kept[:10].all()
    pruned = blob_flights(t, x[:, kept], near, ORIGIN, DX, mass[kept], mass[kept])
    assert ([(np.flatnonzero(kept)[fl.members].tolist(), fl.start, fl.stop, fl.acceleration) for fl in pruned]
            == [(fl.members.tolist(), fl.start, fl.stop, fl.acceleration) for fl in flights])
    # the contact left in: the passing blob's one long "flight" is not free fall
    blind = blob_flights(t, x, np.zeros_like(held), ORIGIN, DX, mass, mass)
    (whole,) = [fl for fl in blind if set(fl.members) == set(range(8))]
    assert abs(whole.acceleration / G - 1) > 0.05


def test_a_blob_carrying_mass_scaled_skin_falls_at_its_weight_over_its_inertia():
    """A free blob whose particles have mass-scaled inertia (a torn flake: inertia s m_phys, weight m_phys g)
    accelerates at g sum m_phys / sum m: the expected value the fit is judged against; no flight under 4 samples,
    and an empty record has no acceleration."""
    t = np.arange(6) * 2e-3
    z = 0.1 + 0.5 * G * 0.5 * t ** 2
    x = np.stack(np.broadcast_arrays(0.0, 0.0, z[:, None] + np.array([0.0, 1e-3])), -1)
    flights = blob_flights(t, x, np.zeros((6, 2), bool), ORIGIN, DX, np.array([1.0, 3.0]), np.array([1.0, 1.0]))
    assert flights[0].expected == pytest.approx(0.5 * G) and flights[0].acceleration == pytest.approx(0.5 * G)
    assert blob_flights(t[:3], x[:3], np.zeros((3, 2), bool), ORIGIN, DX, np.ones(2), np.ones(2)) == []
    assert flight_summary([])["acceleration"] is None
