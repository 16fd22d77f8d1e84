"""Surface contact with rigid colliders (plane, sphere, capsule) and particle pins: the velocity change a collider
or a pin gives a particle whose surface touches it, its impulse on the fingers' reactions, and the kernels
that move colliders and pins along their paths every substep.
"""
from __future__ import annotations

import warp as wp

from .structs import COLLIDER_CAPSULE, COLLIDER_PLANE, KERNEL_OPTIONS, Colliders, GridStep

wp.set_module_options(KERNEL_OPTIONS)


@wp.func
def collider_distance(col: Colliders, c: int, x: wp.vec3) -> wp.vec4:
    """Signed distance (m, 4th lane; > 0 on the material's side) of x from collider c and the unit normal at the
    closest surface point pointing towards the material (first three lanes)."""
    kind = col.kind[c]
    a = col.a[c]
    if kind == COLLIDER_PLANE:
        n = col.b[c]
        return wp.vec4(n[0], n[1], n[2], wp.dot(x - a, n))
    centre = a
    if kind == COLLIDER_CAPSULE:
        ab = col.b[c] - a
        t = wp.clamp(wp.dot(x - a, ab) / wp.max(wp.dot(ab, ab), 1.0e-30), 0.0, 1.0)
        centre = a + t * ab
    d = x - centre
    ln = wp.length(d)
    n = wp.vec3(0.0, 0.0, 1.0)
    if ln > 0.0:
        n = d / ln
    return wp.vec4(n[0], n[1], n[2], ln - col.radius[c])


@wp.struct
class ContactResult:
    v: wp.vec3  # particle velocity after the contact impulses, m/s
    A: wp.mat33  # affine momentum (kg/s) placing each impulse at its contact point


@wp.func
def record_impulse(col: Colliders, finger: int, mass: float, dv: wp.vec3, v_new: wp.vec3):
    """A collider's or pin's velocity change dv (m/s) of a particle of ``mass`` (kg): its impulse m dv (N s) joins
    ``finger``'s reaction (none if < 0) and its work m dv . v_new (J) the boundary work."""
    if finger >= 0:
        wp.atomic_add(col.impulse, finger, mass * dv)
    wp.atomic_add(col.work, 0, wp.float64(mass * wp.dot(dv, v_new)))


@wp.func
def contact_velocity(col: Colliders, x: wp.vec3, v: wp.vec3, C: wp.mat33, F: wp.mat33, tau: wp.mat33, vol: float,
                     radius: float, mass: float, dt: float, inv_dx: float, field: int) -> ContactResult:
    """Surface contact of one particle (centre x, m; velocity v, m/s; velocity gradient C, 1/s; deformation
    gradient F; radius = its reach, half its undeformed spacing or a thin wall's face, m, ``contact_reach``; mass,
    kg; velocity field ``field``) with the colliders that act on its field (``col.field``: that field or < 0,
    all), before its P2G over the coming substep dt (s).

    The particle is the ellipsoid x + F X, |X| <= radius: towards collider c (normal n at the closest surface point,
    signed distance phi_c(x)) it reaches r = radius |F^T n|, so its surface point x - r n has the gap
    g = phi_c(x) - r and, by the particle's affine velocity field, the velocity u = v - r C n.  That point touches
    the collider when g would close within dt: the relative normal velocity u_n = (u - v_c) . n must satisfy
    g + dt (u_n - dt a) >= 0, so u_n is raised to -g / dt + dt a where it is lower (a particle that is not reached in
    this substep is left alone: no halo; one that penetrated is pushed back to the surface).  a = max(-n . tau n, 0)
    V0 / (m 2 r) is the push of the material behind it over the substep (its compressive normal Kirchhoff stress
    tau on its cross-section; without it the particle would settle a dt^2 = eps (c dt)^2 / h into the collider).  Constraining the surface point, not the
    centre, lets the material between the centre and the collider deform (the centre of a particle that touches a
    plate does not move with the plate).  The tangential relative velocity then loses at most mu |du_n| (Coulomb;
    mu = 0 frictionless, mu < 0 no slip).  The change du is added to v; the impulse J = m du enters the P2G
    momentum with the affine term 4/dx^2 J (x_c - x)^T (returned in ``A``), which moves its first moment on the
    grid, sum_i w_i J_i (x_i - x), from the particle centre to the contact point x_c = x - r n (the B-spline's
    second moment is dx^2/4 I) while its total stays J: the push enters the grid as a traction at the material's
    surface, not as a body force centred half a particle inside (which left the layers next to a plate
    under-strained).  J is added to the collider's finger reaction (N s) with its work J . v_new (J)."""
    vn = v
    A = wp.mat33(0.0)
    for c in range(col.count):
        cf = col.field[c]
        if cf >= 0 and cf != field:
            continue
        dn = collider_distance(col, c, x)
        n = wp.vec3(dn[0], dn[1], dn[2])
        r = radius * wp.length(wp.transpose(F) @ n)
        gap = dn[3] - r
        vc = col.vel[c]
        rel = vn - r * (C @ n) - vc
        un = wp.dot(rel, n)
        # the material behind pushes the particle on with its normal stress over the coming substep
        push = wp.max(-wp.dot(n, tau @ n), 0.0) * vol / (mass * 2.0 * r)
        need = -gap / dt - un + dt * push
        if need > 0.0:
            vt = rel - un * n
            lt = wp.length(vt)
            mu = col.mu[c]
            keep = float(1.0)
            if mu < 0.0 or lt <= mu * need:
                keep = 0.0
            elif mu > 0.0:
                keep = 1.0 - mu * need / lt
            dv = need * n + (keep - 1.0) * vt
            new = vn + dv
            vn = new
            A = A - (4.0 * inv_dx * inv_dx * mass * r) * wp.outer(dv, n)
            record_impulse(col, col.finger[c], mass, dv, new)
    res = ContactResult()
    res.v = vn
    res.A = A
    return res


@wp.func
def pin_velocity(col: Colliders, slot: int, x: wp.vec3, v: wp.vec3, C: wp.mat33, F: wp.mat33, radius: float,
                 mass: float, dt: float, inv_dx: float) -> ContactResult:
    """A pinned particle (``col.pin_slot``): its surface point x_s = x + r n (n the surface's outward normal, r =
    arm radius |F^T n|, as in :func:`contact_velocity`, arm = ``col.pin_arm``: 1, or 0 for a particle that is a whole
    wall thinner than its spacing, whose centre is pinned) is driven along its prescribed path, which is at ``col.pin_y``
    now and moves at ``col.pin_v``: the point's velocity u = v + r C n becomes pin_v + (pin_y - x_s) / dt over the
    coming substep dt (the second term takes back what the grid's blend of the particle with its neighbours left of
    the last one), all of it or, with ``col.pin_slip``, its normal component; a pin with ``col.pin_free`` does not
    hold the point back when it moves out along n faster than that (the table's hold, :mod:`tasks.physics.table_hold`:
    its points are held from slipping and lifting but may be pressed down onto the table, which then acts on them).  The change du enters the P2G like a
    collider's: v + du, with the affine term 4/dx^2 m du (x_s - x)^T, so the impulse J = m du acts at the surface
    point, where the finger is, not as a body force at the centre.  J is added to the pin's finger reaction (N s)
    with its work J . v_new (J).  Unlike grid-node Dirichlet conditions, no node is held: the neighbours of a
    pinned particle move with the material, so no layer next to the boundary is held rigid."""
    n = col.pin_n[slot]
    r = col.pin_arm[slot] * radius * wp.length(wp.transpose(F) @ n)
    xs = x + r * n
    u = v + r * (C @ n)
    du = col.pin_v[slot] + (col.pin_y[slot] - xs) / dt - u
    if col.pin_slip != 0:
        du = wp.dot(du, n) * n
    if col.pin_free[slot] != 0 and wp.dot(du, n) < 0.0:  # moving out along n faster than its path: not held back
        du = du - wp.dot(du, n) * n
    new = v + du
    record_impulse(col, col.pin_finger[slot], mass, du, new)
    res = ContactResult()
    res.v = new
    res.A = (4.0 * inv_dx * inv_dx * mass * r) * wp.outer(du, n)
    return res


@wp.kernel
def k_collider_advance(col: Colliders, gs: GridStep):
    """Move every collider by dt = ``gs.dt`` times its velocity (rigid translation, m)."""
    c = wp.tid()
    d = gs.dt * col.vel[c]
    col.a[c] = col.a[c] + d
    if col.kind[c] == COLLIDER_CAPSULE:
        col.b[c] = col.b[c] + d


@wp.kernel
def k_pin_advance(col: Colliders, gs: GridStep):
    """Move every pin's target point along its path by dt = ``gs.dt`` times its velocity (m)."""
    i = wp.tid()
    col.pin_y[i] = col.pin_y[i] + gs.dt * col.pin_v[i]
