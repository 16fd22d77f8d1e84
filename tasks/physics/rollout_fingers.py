"""The fingers of the rollout, frame by frame (paper sec. 3.2, eq. 3; :mod:`tasks.physics.mpm_rollout`'s module
doc): Dirichlet points on the grid (``mpm.fingers=dirichlet``), particle pins (``particles``, the default), fingertip
colliders (``collider``), and the force-driven push of the no_dirichlet ablation with its balance
(``simulation.force_balance``) and its push through a rupture's openings."""
from __future__ import annotations

from typing import Any, Mapping, Optional

import numpy as np
from scipy.spatial import cKDTree

from conf.hand import FINGERTIP_PAD_RADIUS, N_FINGERS
from tasks.physics.labels import CORE
from tasks.physics.mpm import Collider, DirichletPoints, ForcePatch, MPMSolver, ParticlePins
from tasks.physics.rollout_scene import Scene


def boundary_points(bc: Optional[DirichletPoints], push: Optional[list[ForcePatch]], t: float) -> Optional[np.ndarray]:
    """(n, xyz) m: where the frame's Dirichlet points (advected with their velocities) or force points (at the
    frame start) are ``t`` s after the frame start (None: neither)."""
    if bc is not None:
        return np.asarray(bc.positions) + (t * np.asarray(bc.velocities) if bc.advect else 0.0)
    return None if not push else np.concatenate([np.asarray(p.positions).reshape(-1, 3) for p in push])


def dirichlet_points(scene: Scene, field: Mapping[str, np.ndarray], f: int, torn: np.ndarray,
                     contact_tolerance: float) -> tuple[Optional[DirichletPoints], np.ndarray, np.ndarray]:
    """The Dirichlet conditions of frame f (module doc): the constrained, untorn points a finger pushes or holds,
    driven to their eq. 3 targets within one frame.  Returns (conditions or None, point indices, targets (m))."""
    disp, finger_of = field["displacement"], field["finger"]
    idx = np.flatnonzero(field["constrained"][f] & ~torn)
    target_x = np.zeros((0, 3))
    if len(idx):
        current = scene.solver.tracer_positions()[idx].astype(np.float64)
        target_x = scene.surface0[idx] + disp[f, idx]
        # unilateral contact: a finger pushes or holds, it never pulls material outwards
        inward = scene.regions.direction[f, finger_of[f, idx]]
        gap = np.einsum("ij,ij->i", target_x - current, inward)
        retreating = np.einsum("ij,ij->i", disp[f, idx] - disp[f - 1, idx], inward) < 0.0
        push_or_hold = gap >= np.where(retreating, 0.0, -contact_tolerance)
        idx, current, target_x = idx[push_or_hold], current[push_or_hold], target_x[push_or_hold]
    if not len(idx):
        return None, idx, target_x
    bc = DirichletPoints(positions=current, velocities=(target_x - current) / scene.frame_dt,
                         finger_ids=finger_of[f, idx].astype(np.int32))
    return bc, idx, target_x


def particle_pins(scene: Scene, bc: Optional[DirichletPoints], idx: np.ndarray, target_x: np.ndarray, f: int,
                  field: Mapping[str, np.ndarray]) -> Optional[ParticlePins]:
    """``mpm.fingers = particles``: the Dirichlet conditions of frame f (:func:`dirichlet_points`: surface points
    ``idx``, targets ``target_x``) on the particles instead of the grid nodes.  Every particle a constrained point
    is embedded in (its anchors) has its surface point, along the finger's outward patch normal, driven by the
    mean displacement its points still need (target - where they are), so the points move by that much; the push
    acts on those particles only, at their surface (no node is held, so no layer next to the finger is held rigid)
    or, on a wall thinner than the spacing (``scene.thin_wall``: ``sampling.thin_wall_layers`` particle layers
    within it), at their centres (:class:`ParticlePins` ``arms``), and its impulses are the finger's reaction."""
    if bc is None:
        return None
    anchors = scene.solver.tracer_anchor_particles()[idx]  # (point, anchor)
    point = np.repeat(np.arange(len(idx)), anchors.shape[1])
    particles, which = np.unique(anchors.reshape(-1), return_inverse=True)
    count = np.bincount(which, minlength=len(particles)).astype(np.float64)[:, None]
    finger = field["finger"][f, idx]
    outward = -scene.regions.direction[f, finger]
    need = (target_x - bc.positions)[point]
    move = np.stack([np.bincount(which, need[:, c], len(particles)) for c in range(3)], 1)
    normal = np.stack([np.bincount(which, outward[point, c], len(particles)) for c in range(3)], 1)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    first = np.full(len(particles), -1, np.int64)
    first[which[::-1]] = point[::-1]  # each particle's first point gives its finger
    arms = np.full(len(particles), 0.0 if scene.thin_wall else 1.0)
    start = scene.solver.surface_points(particles, normal, arms)
    return ParticlePins(particles, start + move / count, normal, finger[first].astype(np.int32), arms=arms)


def fingertip_travel(field: Mapping[str, np.ndarray], f: int) -> np.ndarray:
    """The eq. 3 amplitude eta c_k,t (m) of every finger at frame f, as the field multiplied it in (its
    ``amplitude``, :func:`tasks.control.dirichlet_field.dirichlet_field`): how far the patch centre, where phi_k = 1,
    moves along the inward normal d_k.  (finger,); 0 for a finger whose patch is inactive."""
    return np.asarray(field["amplitude"][f], np.float64)


def fingertip_centres(field: Mapping[str, np.ndarray], patches: Mapping[str, np.ndarray], f: int,
                      radius: float) -> np.ndarray:
    """Centre (m) of each finger's fingertip sphere (``radius`` m) at frame f (finger, xyz): its lowest point is
    the patch centre moved inwards by the eq. 3 amplitude eta c_k,t (:func:`fingertip_travel`), so at zero force it
    touches the rest surface and at frame f it reaches the target the field prescribes at the patch centre where no
    other patch overlaps (overlapping patches add to the field there, not to the finger's own travel; until
    2026-12-05 the travel was a least-squares fit of the field over the finger's points, which took in the overlap:
    on the default rubber ball 26 % deeper than eta c_k in the median frame and finger, up to 87 %)."""
    outward = patches["patch_normals"][f].astype(np.float64)
    travel = fingertip_travel(field, f)
    return patches["patch_centers"][f].astype(np.float64) + (radius - travel)[:, None] * outward


def finger_colliders(solver: MPMSolver, surface0: np.ndarray, field: Mapping[str, np.ndarray],
                     patches: Mapping[str, np.ndarray], f: int, torn: np.ndarray, frame_dt: float,
                     friction: float = 0.0) -> list[Collider]:
    """The fingers of frame f under ``mpm.fingers = collider`` (module doc): a rigid sphere of the fingertip pad
    radius per active finger, from its place at frame f - 1 to its place at frame f (:func:`fingertip_centres`) in
    the frame's time, i.e. velocity = displacement / frame_dt (m/s).  A finger that was not active at frame f - 1
    starts where it just touches the material (:func:`_touching`), not at the rest surface: particle surfaces stick
    out of it by up to the sampling jitter, and a sphere placed over them would kick them out within one substep.
    The contact is unilateral by construction (a collider pushes, never pulls), frictionless or with Coulomb
    ``friction`` (``mpm.finger_friction``).  A finger whose patch centre lies on torn skin (``torn`` (point,) bool
    over the rest surface points ``surface0`` (point, xyz) m: the one nearest to the centre ruptured) no longer
    presses: the opening is free."""
    radius, active = FINGERTIP_PAD_RADIUS, patches["patch_active"]
    end = fingertip_centres(field, patches, f, radius)
    start = fingertip_centres(field, patches, f - 1, radius)
    centres = patches["patch_centers"][f].astype(np.float64)
    nearest = np.argmin(((surface0[None, :, :] - centres[:, None, :]) ** 2).sum(axis=-1), axis=1)
    on = [k for k in range(N_FINGERS) if active[f, k] and not torn[nearest[k]]]
    arriving = [k for k in on if not active[f - 1, k]]
    if arriving:
        x, half = solver.positions().astype(np.float64), solver.contact_radii()
        for k in arriving:
            start[k] = _touching(x, half, centres[k] + radius * patches["patch_normals"][f, k],
                                 patches["patch_normals"][f, k], radius)
    return [Collider("sphere", start[k], radius=radius, velocity=(end[k] - start[k]) / frame_dt,
                     friction=float(friction), finger_id=k) for k in on]


def _touching(x: np.ndarray, half: np.ndarray, centre: np.ndarray, outward: np.ndarray, radius: float) -> np.ndarray:
    """The sphere (``radius`` m) at ``centre`` (m) moved out along ``outward`` until no particle surface (centre
    ``x`` (particle, xyz) m + ``half`` its half spacing, m) lies inside it (a few fixed-point steps)."""
    for _ in range(4):
        depth = float(np.max(radius + half - np.linalg.norm(x - centre, axis=1), initial=0.0))
        if depth <= 1e-6 * radius:
            break
        centre = centre + depth * np.asarray(outward, np.float64)
    return centre


def force_patch(scene: Scene, field: Mapping[str, np.ndarray], forces: np.ndarray,
                patches: Mapping[str, np.ndarray], f: int, torn: np.ndarray, sim: Mapping[str, Any],
                openings: Optional[tuple[np.ndarray, np.ndarray]] = None,
                beneath: Optional[np.ndarray] = None) -> Optional[list[ForcePatch]]:
    """The force-mode push of frame f (the no_dirichlet ablation): a total force ``force_per_coefficient *
    c_k,t`` N per active finger along its inward patch normal, spread over its constrained, untorn points.

    1. The skin: the points are the surface tracers, re-placed every substep (``ForcePatch.tracers``): the push
    follows the skin.  (Fixed for a frame, they were left behind by a torn arm moving at 3 m/s, 10 cm per frame, and
    the finger's whole force went to the fringe mass still under them, 2.3 N on 4e-5 kg: the divergence, dt 1e-9 s,
    of the plush toy pushed with balanced fingers after its rupture.)  A finger that punctured the skin no longer
    presses on its torn points: their share of its force (torn / constrained points of its patch) goes 2. to the
    stuffing or pulp beneath its opening (``simulation.torn_finger_push=beneath``), as far as the grip needs it
    (:func:`grip_closing_share`): the core particles (CORE) chosen at the rupture within two grid cells of the
    finger's torn points and of the interior released under it (``beneath`` (particle,) the finger pushing each,
    -1 none; :func:`stuffing_beneath`), of which those still within ``release_radius`` + two cells of the torn
    points where they are now (``openings``: the torn surface points and their fingers) are pushed, on their own
    positions (``ForcePatch.particles``).  The finger presses on through the hole onto what lies under it; what it
    pushed deep leaves its reach (the whole set pushed with the whole share carried particles out of the plush
    toy's far side, 8 cm from its centre at 1.9 m/s, J guard at frame 63 of seed 0).  Without such particles
    (``torn_finger_push=none``, or a hollow can whose cola is a fluid) that share is dropped: the released material
    offers no support.  (Concentrating the whole force on the few skin points left beside an opening crushed the
    loose stuffing there to det F = 3e-4; spread over the torn skin too, it followed the flaps as they folded away
    and flung 7.4 % of the plush toy's torn skin off the toy.)  3. The fingers' forces are then
    balanced (``simulation.force_balance``, :func:`balanced_push`; each finger's moment arm from the centre of its
    points, skin and beneath weighted by their shares), before and after a rupture: the hand still closes its grip
    on a torn toy.  Whether the push is a grasp (two fingers against each other) or a poke is read from the
    fingers' intended push, torn patches included: a finger that punctured the skin still closes the grip.
    (Unbalanced after its rupture, the force-driven plush toy's index pushed 5.8 N against the pinky's 1.7 N and
    toppled it; balanced, both push 1.8 N.  With the torn thumb's share dropped, its four fingers left side by
    side cannot close the grip within their friction cones and shoved it over in two of three sampling seeds.)"""
    finger_of = field["finger"][f]
    constrained = field["constrained"][f]
    idx = np.flatnonzero(constrained & ~torn)
    surface = scene.solver.tracer_positions()
    deep, x = np.zeros(0, np.int64), None
    if beneath is not None and openings is not None and len(openings[0]):
        x = scene.solver.positions()
        reach = float(sim["release_radius"]) + 2.0 * scene.dx
        deep = np.flatnonzero(stuffing_beneath(x, beneath >= 0, surface[openings[0]], openings[1], reach) >= 0)
    # 1.-2. each finger's intended force and the shares with a point of application (skin, beneath)
    intended, on_skin, below = np.zeros((N_FINGERS, 3)), np.zeros(N_FINGERS), np.zeros(N_FINGERS)
    for k in range(N_FINGERS):
        patch = int((constrained & (finger_of == k)).sum())
        if patches["patch_active"][f, k] and patch:
            intended[k] = float(sim["force_per_coefficient"]) * forces[f, k] * -patches["patch_normals"][f, k]
            on_skin[k] = int((finger_of[idx] == k).sum()) / patch
            below[k] = (1.0 - on_skin[k]) * bool((beneath[deep] == k).any()) if len(deep) else 0.0
    grasp = bool((intended @ intended.T < 0.0).any())
    below *= grip_closing_share(intended * on_skin[:, None], intended * below[:, None])
    applied = on_skin + below
    if not (applied > 0).any():
        return None
    skin_x, skin_k = surface[idx], finger_of[idx].astype(np.int32)
    deep_x, deep_k = (x[deep], beneath[deep].astype(np.int32)) if len(deep) else (None, None)
    centres = np.zeros((N_FINGERS, 3))
    for k in np.flatnonzero(applied > 0):
        if on_skin[k]:
            centres[k] += on_skin[k] * skin_x[skin_k == k].mean(axis=0)
        if below[k]:
            centres[k] += below[k] * deep_x[deep_k == k].mean(axis=0)
        centres[k] /= applied[k]
    # 3. the balance of the whole push, then each finger's force split between its skin and what lies beneath
    push = balanced_push(intended * applied[:, None], str(sim["force_balance"]), float(sim["force_balance_friction"]),
                         centres, grasp=grasp)
    part = np.divide(1.0, applied, out=np.zeros(N_FINGERS), where=applied > 0)[:, None] * push
    out = []
    if len(idx):
        out.append(ForcePatch(positions=skin_x, finger_ids=skin_k, tracers=idx, forces=on_skin[:, None] * part))
    if below.any():
        out.append(ForcePatch(positions=deep_x, finger_ids=deep_k, particles=deep, forces=below[:, None] * part))
    return out


def grip_closing_share(skin: np.ndarray, beneath: np.ndarray) -> float:
    """The share s in [0, 1] of the push through the openings ``beneath`` (finger, xyz) N that leaves the fingers'
    push ``skin + s beneath`` (N) the least net force, s = clip(-N_skin . N_b / |N_b|^2, 0, 1) (N the sums over
    the fingers): the stuffing under an opening carries what closes the grip, no more.  It is crushable (the plush
    toy's yields at 1 kPa: 0.4 N under a 4 cm^2 fingertip) and offers a finger pressing into it only the reaction
    the hand's closed force loop asks of it.  (Pushed with their whole force, the three fingers through their
    openings of seed 0 of the force-driven plush toy tore its head off, J guard at frame 54.)"""
    net = np.asarray(beneath).sum(axis=0)
    size = float(net @ net)
    return float(np.clip(-np.asarray(skin).sum(axis=0) @ net / size, 0.0, 1.0)) if size > 0 else 0.0


def beneath_openings(x: np.ndarray, labels: np.ndarray, released: np.ndarray, surface: np.ndarray,
                      openings: tuple[np.ndarray, np.ndarray], centers: np.ndarray, fingers: list[int],
                      radius: float, depth: float) -> np.ndarray:
    """:func:`stuffing_beneath` at the rupture: each finger's opening is its torn surface points (``openings``:
    indices into ``surface`` (point, xyz) m, where the skin was as it tore, and their fingers) and, for the fingers
    that punctured it (``fingers``, patch centres ``centers`` m), the interior released within ``radius`` m of its
    centre (particles ``x`` m, ``released`` bool)."""
    points, owner = [surface[openings[0]]], [openings[1]]
    for k in fingers:
        out = released & (np.linalg.norm(x - centers[k], axis=1) <= radius)
        points.append(x[out])
        owner.append(np.full(int(out.sum()), k))
    return stuffing_beneath(x, labels == CORE, np.concatenate(points), np.concatenate(owner).astype(np.int32),
                            depth)


def stuffing_beneath(x: np.ndarray, candidates: np.ndarray, opening: np.ndarray, fingers: np.ndarray,
                     depth: float) -> np.ndarray:
    """(particle,) int32: the finger (0..4) that presses through its opening on each particle, -1 none: the
    ``candidates`` (particle,) bool - at the rupture the core (label CORE: the stuffing or pulp that stays part of
    the body), later the core chosen then - within ``depth`` m of the finger's ``opening`` points (n, xyz) m
    (``fingers`` (n,) the finger of each); the nearest finger where two reach.  ``x`` (particle, xyz) m.  The
    released interior itself is not pushed: it leaves through the opening (the stuffing's bulge, the juice)."""
    out = np.full(len(x), -1, np.int32)
    core = np.flatnonzero(candidates)
    if not len(core) or not len(opening):
        return out
    dist, nearest = cKDTree(np.asarray(opening, np.float64)).query(x[core], distance_upper_bound=depth)
    hit = np.isfinite(dist)
    out[core[hit]] = np.asarray(fingers)[nearest[hit]]
    return out


def balanced_push(total: np.ndarray, balance: str, friction: float,
                  centres: Optional[np.ndarray] = None, grasp: Optional[bool] = None) -> np.ndarray:
    """The fingers' push (finger, xyz) N with its net force - and under ``wrench`` then its net moment - removed as
    far as the grip can (``simulation.force_balance``, ``simulation.force_balance_friction`` = mu).

    A hand squeezing an object is a closed force loop: what its fingers put on the object sums to zero, force and
    moment.  1. The force (``fingers`` and ``wrench``): the net force F_net = sum_k F_k is taken off the fingers in
    proportion to their force magnitudes, F_k' = F_k - a (|F_k| / W) F_net with W = sum_j |F_j|; at a = 1 the change
    of least sum_k |F_k' - F_k|^2 / |F_k| (each finger keeps its share of the squeeze) with sum_k F_k' = 0.  Along
    its own direction d_k = F_k / |F_k| a finger still pushes, F_k' . d_k = |F_k| (1 - a d_k . F_net / W) >= 0
    (|F_net| <= W), never pulls; the rest of its change, a |F_k| |F_net,perp k| / W, is tangential: the grip's
    friction, which cannot exceed mu times the finger's push.  So a is the largest value <= 1 at which every
    finger's tangential / normal force stays <= mu, a = min(1, min_k mu W / (|F_net,perp k| + mu d_k . F_net)), and
    what remains of the net force (1 - a) F_net is the table's.  2. The moment (``wrench``), about the fingers'
    points of application ``centres`` (finger, xyz) m (:func:`couple_change`): the least change of the same
    weights that cancels the net moment of step 1's forces without touching their net force, scaled by the largest
    b <= 1 that keeps every finger inside its friction cone about d_k (:func:`inside_friction_cones`); (1 - b) of
    that moment is the table's.  In two steps so that the moment never takes friction from the force balance.  Why
    the moment: the force-driven plush toy, its force points following the skin, swayed on the table under the
    moment its force-balanced fingers left (0.028 N m two frames before the rupture; KE/IE 0.123, 85 % of its KE in
    the sway).  The default grasps' force step needs <= 0.74 (a = 1 before any rupture).  A push without two fingers
    against each other (F_j . F_k < 0: one finger, or fingers side by side, the clay's poke) is left as given, for
    the table to carry as under Dirichlet fingers (balanced, a poke would vanish); ``grasp`` (default: that test on
    ``total``) overrides the test, e.g. for a grasp whose opposing finger tore through the skin (the fingers left
    side by side then balance to what they push against each other).  ``none``: the push as given (its net force,
    up to ~50 % of the fingers' sum along the eq. 3 directions, is carried by nothing but the table)."""
    if balance == "none":
        return total
    if balance not in ("wrench", "fingers"):
        raise ValueError(f"simulation.force_balance must be wrench, fingers or none, got {balance!r}")
    if balance == "wrench" and centres is None:
        raise ValueError("balanced_push: simulation.force_balance=wrench needs the fingers' centres")
    if not ((total @ total.T < 0.0).any() if grasp is None else grasp):  # a poke: no two fingers against each other
        return total
    # 1. the net force
    size = np.linalg.norm(total, axis=1)
    net, on = total.sum(axis=0), size > 0
    d = total[on] / size[on, None]
    along = d @ net
    across = np.linalg.norm(net - along[:, None] * d, axis=1)
    limit = across + friction * along  # > 0 where removing the net force uses up that finger's friction
    share = min([1.0, *(friction * size.sum() / limit[limit > 0])])
    balanced = total - share * (size / size.sum())[:, None] * net
    if balance == "fingers":
        return balanced
    # 2. the net moment, within the friction cones
    change = couple_change(balanced, centres, size)
    low, high = 0.0, 1.0
    if not inside_friction_cones(balanced + change, total, friction):
        for _ in range(40):  # the cones are convex and step 1 is inside them: the admissible b form [0, b_max]
            middle = 0.5 * (low + high)
            low, high = (middle, high) if inside_friction_cones(balanced + middle * change, total, friction) \
                else (low, middle)
        high = low
    return balanced + high * change


def couple_change(push: np.ndarray, centres: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """The change (finger, xyz) N of least sum_k |dF_k|^2 / w_k (``weight`` (finger,) w_k >= 0: |F_k| of the given
    push) that cancels the net moment of ``push`` (finger, xyz) N acting at ``centres`` (finger, xyz) m and adds no
    net force: dF_k = w_k m x r_k with r_k = centre_k - c (c the w-weighted mean centre, so sum_k dF_k = m x sum_k
    w_k r_k = 0) and m = -J^+ M, M = sum_k r_k x push_k, J = sum_k w_k (|r_k|^2 I - r_k r_k^T) (its Lagrange
    condition; J is the fingers' "inertia" about c, and its pseudo-inverse leaves the moment about the line of
    collinear fingers, which forces through those points cannot make, to the table)."""
    weight = np.asarray(weight, np.float64)
    if not weight.sum() > 0:
        return np.zeros_like(push)
    lever = centres - (weight / weight.sum()) @ centres
    moment = np.cross(lever, push).sum(axis=0)
    inertia = np.einsum("k,kij->ij", weight, (lever * lever).sum(axis=1)[:, None, None] * np.eye(3)
                        - lever[:, :, None] * lever[:, None, :])
    m = -np.linalg.pinv(inertia, rcond=1e-9, hermitian=True) @ moment
    return weight[:, None] * np.cross(m, lever)


def inside_friction_cones(push: np.ndarray, given: np.ndarray, friction: float) -> bool:
    """Whether every finger's ``push`` (finger, xyz) N lies in its friction cone about the direction of its
    ``given`` push (tangential <= ``friction`` x normal, normal >= 0; fingers with no given push are skipped)."""
    size = np.linalg.norm(given, axis=1)
    d = given[size > 0] / size[size > 0, None]
    normal = np.einsum("ij,ij->i", push[size > 0], d)
    tangential = np.linalg.norm(push[size > 0] - normal[:, None] * d, axis=1)
    return bool(np.all(tangential <= friction * normal * (1.0 + 1e-12) + 1e-15))
