"""Known-answer contact cases of the MPM solver: grid-node contact against surface (particle) contact.

Two closed forms, each run with ``mpm.contact = grid`` (the solver's floor acts on grid nodes, a plate is a set of
slip :class:`~tasks.physics.mpm.inputs.DirichletPoints`) and ``surface`` (floor and plate are plane
:class:`~tasks.physics.mpm.inputs.Collider` s acting on the particles that touch them):

* Hertz (1882; Johnson, Contact Mechanics, sec. 4.2): an elastic sphere (radius R) pressed by a rigid frictionless
  flat with approach d carries F = 4/3 E* sqrt(R) d^1.5, E* = E / (1 - nu^2), over a contact circle of radius
  a = sqrt(R d).  The whole sphere is squeezed between two flats, each approaching its centre by d (see
  :func:`hertz_case`).  The sphere is sampled in concentric shells (:func:`sphere_shell_particles`): a
  lattice-sampled sphere has a flat bottom facet of radius ~ sqrt(R h) (8 mm for R = 35 mm at R / dx = 8), a
  pre-indentation as large as the depths measured.
* Uniaxial compression: a cube (side L) between two frictionless plates with its lateral faces free carries
  F = E A eps at the nominal strain eps = travel / L (A = L^2), for any nu.

Both load slowly (quasi-static: loading time many times the bar-wave transit time) with a ramped plate speed, no
gravity, 2 x 2 x 2 particles per cell.  :func:`hertz_case` and :func:`uniaxial_case` return the measured and
closed-form forces; ``python -m flows.studies.contact`` prints the error against the grid spacing and the run time.
"""
from __future__ import annotations

import time
from typing import Optional

import numpy as np

from conf.hand import FINGERTIP_PAD_RADIUS, N_FINGERS
from tasks.control.dirichlet_field import dirichlet_field
from tasks.physics.mpm import Collider, DirichletPoints, Material, MPMSolver, ParticlePins
from tasks.physics.rollout_fingers import finger_colliders, fingertip_travel
from tasks.physics.table_hold import join_pins, table_hold

HERTZ_R = 0.035  # m (the sphere: R = 35 mm, E = 2 MPa, nu = 0.45)
HERTZ_E = 2.0e6  # Pa
HERTZ_NU = 0.45
DENSITY = 1000.0  # kg/m^3
HERTZ_DEPTHS = (0.001, 0.002, 0.003, 0.004)  # m, the 1-4 mm


def hertz_force(d: np.ndarray, R: float = HERTZ_R, E: float = HERTZ_E, nu: float = HERTZ_NU) -> np.ndarray:
    """Hertz force (N) of a sphere (radius R, m; E, Pa; nu) on a rigid flat at approach d (m)."""
    return 4.0 / 3.0 * E / (1.0 - nu ** 2) * np.sqrt(R) * np.maximum(np.asarray(d, float), 0.0) ** 1.5


def sphere_shell_particles(R: float, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Particles filling a sphere of radius R (m) centred at the origin with spacing ~h (m): concentric shells of
    radius R - (k + 1/2) h, each with round(4 pi r^2 / h^2) Fibonacci points sharing the shell's volume, so the
    outer particles' surfaces (centre + h / 2) lie on the sphere.  Returns positions (N, 3) and volumes (N,)."""
    pos, vol = [], []
    for k in range(int(round(R / h))):
        r = R - (k + 0.5) * h
        n = max(1, int(round(4.0 * np.pi * r * r / (h * h))))
        i = np.arange(n) + 0.5
        z = 1.0 - 2.0 * i / n
        rho = np.sqrt(1.0 - z * z)
        th = np.pi * (1.0 + 5.0 ** 0.5) * i
        pos.append(r * np.stack([rho * np.cos(th), rho * np.sin(th), z], axis=1))
        vol.append(np.full(n, 4.0 / 3.0 * np.pi * ((r + h / 2) ** 3 - max(r - h / 2, 0.0) ** 3) / n))
    return np.concatenate(pos), np.concatenate(vol)


def _plate_points(half_width: float, h: float, z: float) -> np.ndarray:
    """A square of points (spacing h, m) at height z covering [-half_width, half_width]^2: a grid-mode plate."""
    g = np.arange(-half_width, half_width + 1e-12, h)
    xx, yy = np.meshgrid(g, g, indexing="ij")
    return np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, z)], axis=1)


def _ramped_speed(t: float, total: float, travel: float, ramp: float = 0.2) -> float:
    """Plate speed (m/s) at time t of a loading that reaches ``travel`` (m) at ``total`` (s): linear ramp over the
    first ``ramp`` fraction, then constant."""
    v = travel / (total * (1.0 - ramp / 2.0))
    return v * min(1.0, t / (ramp * total))


def _press(solver: MPMSolver, plate: str, plate_z: float, half_width: float, travel: float, total: float,
           n_frames: int, on_frame, fixed: Optional[object] = None, mirror_z: Optional[float] = None,
           hold_frames: int = 0) -> None:
    """Move a frictionless plate (normal -z, finger 1) down by ``travel`` (m) over ``total`` (s), starting at
    ``plate_z``: a plane collider (``plate = surface``) or slip Dirichlet points (``grid``), next to the static
    boundary ``fixed`` (a Collider, DirichletPoints or None) or, with ``mirror_z`` (m), a second plate of the same
    kind (normal +z, finger 0) starting there and moving up as the first moves down (a symmetric squeeze), then
    hold the plates still for ``hold_frames`` more frames of the same length; ``on_frame(f, travel_now, stats)``
    after every frame (travel of each plate)."""
    fdt = total / n_frames
    z, zm = plate_z, mirror_z
    h = np.cbrt(float(solver.volumes()[0]))
    down = np.array([0.0, 0.0, 1.0])
    plates = [(-down, 1)] + ([(down, 0)] if mirror_z is not None else [])
    for f in range(n_frames + hold_frames):
        vz = -_ramped_speed((f + 0.5) * fdt, total, travel) if f < n_frames else 0.0
        coll = [fixed] if isinstance(fixed, Collider) else []
        bcs = [fixed] if isinstance(fixed, DirichletPoints) else []
        pins = None
        for normal, finger in plates:
            at, v = (z, vz) if finger == 1 else (zm, -vz)
            if plate == "pins":  # the particles whose surface touches the plate: their surface points follow it
                x = solver.positions()
                top = x[:, 2] > at - h
                target = x[top].copy()
                target[:, 2] = at + v * fdt
                pins = ParticlePins(np.flatnonzero(top), target, np.tile(-normal, (int(top.sum()), 1)),
                                    np.full(int(top.sum()), finger), slip=True)
            elif plate == "grid":
                pts = _plate_points(half_width, h, at)
                bcs.append(DirichletPoints(pts, np.tile([0.0, 0.0, v], (len(pts), 1)), np.full(len(pts), finger),
                                           normals=np.tile(normal, (len(pts), 1))))
            else:
                coll.append(Collider("plane", (0.0, 0.0, at), normal, velocity=(0.0, 0.0, v), finger_id=finger))
        if isinstance(fixed, ParticlePins):
            pins = join_pins(pins, fixed)
        st = solver.step_frame(fdt, dirichlet=bcs or None, colliders=coll or None, pins=pins)
        z += vz * fdt
        zm = None if zm is None else zm - vz * fdt
        on_frame(f, plate_z - z, st)


def hertz_case(contact: str, cells_per_radius: int, depth: float = 0.004, load_transits: float = 12.0,
               n_frames: int = 40, R: float = HERTZ_R, E: float = HERTZ_E, nu: float = HERTZ_NU,
               depths: tuple[float, ...] = HERTZ_DEPTHS) -> dict:
    """The whole sphere squeezed between two frictionless flats (plane colliders with ``contact = surface``, slip
    Dirichlet points with ``grid``), each moving towards its centre by ``depth`` (m) over ``load_transits``
    bar-wave transits of R; ``cells_per_radius`` = R / dx.

    Each flat then has Hertz's contact with the approach d = its own travel, and by symmetry the centre stays at
    rest (no rigid-body mode: a sphere driven by one flat would bounce on its Hertzian spring, period ~15 ms, far
    longer than an affordable loading).  The cheaper half sphere with its equator (the symmetry plane) driven by
    slip Dirichlet points read 12-15 points more force error at nu = 0.45 (3-4 at nu = 0, 13-26 at 0.49): the
    points hold a ~1-cell layer at zero axial strain, which cut the equator's Poisson expansion by 60-75 % like a
    stiff ring.  What remains against Hertz is the finite sphere at finite strain
    (:mod:`tasks.verification.sphere_fe`).  Returns per frame ``depth`` (m, each flat's travel, frame ends),
    ``force`` (N, frame mean: the mean of the two flats' reactions) and the bottom contact ``radius`` (m, from the
    number N of particles within h / 20 of the lowest one, a = h sqrt(N / pi): the flattened patch, which a grid
    flat holds off itself, at the frame ends); at
    ``depths``: ``at`` (m), ``force_at``, ``hertz_at`` (N), ``force_error``, ``radius_at``, ``radius_hertz`` (m),
    ``radius_error``; ``seconds``, ``particles``.
    """
    dx = R / cells_per_radius
    h = dx / 2
    X, vol = sphere_shell_particles(R, h)
    X = X + [0.0, 0.0, R]
    mat = Material(name="sphere", model="fixed_corotated", youngs_modulus=E, poisson_ratio=nu, density=DENSITY)
    cfg = dict(device="cpu", dx=dx, gravity=[0.0, 0.0, 0.0], floor=False, contact=contact, margin_cells=3,
               energy_guard_tolerance=0.0)
    s = MPMSolver(X, vol, mat, config=cfg, label="hertz")
    total = load_transits * R / mat.bar_wave_speed()
    rec: dict[str, list] = {"depth": [], "force": [], "radius": []}

    def on_frame(f, d, st):
        r = np.asarray(st.reaction)
        z = s.positions()[:, 2]
        touching = z <= z.min() + 0.05 * h  # flattened: within h / 20 of the lowest (grid: held off the flat)
        rec["depth"].append(d)
        rec["force"].append(0.5 * float(r[0, 2] - r[1, 2]))
        rec["radius"].append(float(h * np.sqrt(touching.sum() / np.pi)))

    t0 = time.perf_counter()
    _press(s, contact, 2 * R, R / 2, depth, total, n_frames, on_frame, mirror_z=0.0)
    seconds = time.perf_counter() - t0
    out = {k: np.asarray(v) for k, v in rec.items()}
    at = np.asarray(depths, float)
    out.update(at=at, seconds=seconds, particles=len(X), dx=dx, contact=contact)
    out["force_at"] = np.interp(at, frame_mean(out["depth"]), out["force"])
    out["hertz_at"] = hertz_force(at, R, E, nu)
    out["force_error"] = out["force_at"] / out["hertz_at"] - 1.0
    out["radius_at"] = np.interp(at, out["depth"], out["radius"])
    out["radius_hertz"] = np.sqrt(R * at)
    out["radius_error"] = out["radius_at"] / out["radius_hertz"] - 1.0
    return out


def table_hertz_case(contact: str, dx: float, R: float = 0.03, E: float = HERTZ_E, nu: float = HERTZ_NU,
                     travel: float = 0.0085, total: float = 0.15, n_frames: int = 60,
                     depths: tuple[float, ...] = HERTZ_DEPTHS, particles_across_cell: int = 2,
                     hold: str = "none") -> dict:
    """An elastic sphere (radius R, m; E, Pa; nu) resting on the table (``mpm.floor``, frictionless, the table's
    height the solver's default for ``contact``: the lowest particle's surface under ``surface``, its centre under
    ``grid``) and pressed from above by a frictionless plane collider moving down ``travel`` (m) over ``total`` (s,
    ~17 periods of the sphere bouncing on its Hertz spring at 2 mm: quasi-static without a second flat), no gravity,
    grid spacing ``dx`` (m), ``particles_across_cell`` particles per cell along each axis.  Plate and table carry the
    same force F (the plate's reaction, N, frame mean); the table's approach is d = R - (z_c - z_0), z_c the centre of
    mass, z_0 the sphere's initial bottom (m), since in a quasi-static squeeze the centre lies midway between two
    equal contacts.  Returns per frame ``depth`` (m, at frame ends), ``force`` (N), ``radius`` (m, the flattened patch
    at the bottom as :func:`hertz_case` reads it) and at ``depths``: ``force_at``, ``hertz_at``, ``force_ratio``
    (measured / Hertz), ``radius_at``, ``radius_hertz``, ``seconds``, ``particles``, ``floor_height``, ``held`` (how
    many particles the table's ``hold``, :func:`tasks.physics.table_hold.table_hold`, pins: those touching the table
    at the start)."""
    h = dx / particles_across_cell
    X, vol = sphere_shell_particles(R, h)
    X = X + [0.0, 0.0, R]
    mat = Material(name="sphere", model="fixed_corotated", youngs_modulus=E, poisson_ratio=nu, density=DENSITY)
    s = MPMSolver(X, vol, mat, config=dict(device="cpu", dx=dx, gravity=[0.0, 0.0, 0.0], floor=True, contact=contact,
                                           margin_cells=3, energy_guard_tolerance=0.0), label="table_hertz")
    pins = table_hold(s, hold)
    rec: dict[str, list] = {"depth": [], "force": [], "radius": []}

    def on_frame(f, d, st):
        z = s.positions()[:, 2].astype(np.float64)
        rec["depth"].append(R - float(np.average(z, weights=vol)))
        rec["force"].append(-float(np.asarray(st.reaction)[1, 2]))
        rec["radius"].append(float(h * np.sqrt((z <= z.min() + 0.05 * h).sum() / np.pi)))

    t0 = time.perf_counter()
    _press(s, "surface", 2 * R, R, travel, total, n_frames, on_frame, fixed=pins)
    out = {k: np.asarray(v) for k, v in rec.items()}
    at = np.asarray(depths, float)
    out.update(at=at, seconds=time.perf_counter() - t0, particles=len(X), dx=dx, contact=contact,
               floor_height=float(s.floor_height), held=0 if pins is None else len(pins.indices))
    out["force_at"] = np.interp(at, frame_mean(out["depth"]), out["force"])
    out["hertz_at"] = hertz_force(at, R, E, nu)
    out["force_ratio"] = out["force_at"] / out["hertz_at"]
    out["radius_at"] = np.interp(at, out["depth"], out["radius"])
    out["radius_hertz"] = np.sqrt(R * at)
    return out


def body_between_flats(solver: MPMSolver, plate: str, travel: float, duration: float, n_frames: int,
                       hold_frames: int = 0) -> dict:
    """A body already in ``solver`` (e.g. the default grid's hollow rubber ball, its walls in plane stress) squeezed
    between two frictionless flats starting at its particles' top and bottom surfaces (centre +- their contact reach,
    :meth:`MPMSolver.contact_radii`), each moving towards the other by ``travel`` (m) over ``duration`` (s) in
    ``n_frames`` frames (``plate``: ``grid`` slip Dirichlet points, as the default fingers act, or ``surface`` plane
    colliders, with the solver's matching ``mpm.contact``), then held there for ``hold_frames`` frames (an elastic
    body's force stays; a drop is creep).  Compared with :func:`tasks.verification.sphere_fe.sphere_between_flats`
    (``wall``: the hollow sphere's FE reference).  Returns per frame of the press ``depth`` (m, each flat's travel,
    frame ends) and ``force`` (N, frame mean of the two flats' reactions), ``held`` (N, the same per frame of the
    hold), ``pole_gap`` (m, per frame of the press and the hold: how far the body's face on the flats' axis, the
    particles within dx / 2 of it, has left each flat, mean of the two; ~0 while the flat presses it, > 0 where the
    face under the flat's centre has sunk away from it, as a shell dimpling under the flat), ``seconds`` and
    ``substeps`` (of the press)."""
    x = solver.positions()
    half = solver.contact_radii()  # where each particle's surface reaches a flat (a thin wall's: its face)
    top, bottom = float((x[:, 2] + half).max()), float((x[:, 2] - half).min())
    width = 0.5 * float(np.ptp(x[:, :2], axis=0).max()) + 2.0 * solver.dx
    centre = x.astype(np.float64).mean(axis=0)
    on_axis = np.hypot(*(x[:, :2] - centre[:2]).T) < 0.5 * solver.dx
    upper, lower = on_axis & (x[:, 2] > centre[2]), on_axis & (x[:, 2] < centre[2])
    rec: dict[str, list] = {"depth": [], "force": [], "substeps": [], "pole_gap": []}

    def on_frame(f, d, st):
        r = np.asarray(st.reaction)
        rec["depth"].append(d)
        rec["force"].append(0.5 * float(r[0, 2] - r[1, 2]))
        rec["substeps"].append(int(st.substeps))
        z = solver.positions()[:, 2].astype(np.float64)
        gaps = [top - d - float((z[upper] + half[upper]).max()), float((z[lower] - half[lower]).min()) - bottom - d]
        rec["pole_gap"].append(0.5 * sum(gaps))

    t0 = time.perf_counter()
    _press(solver, plate, top, width, travel, duration, n_frames, on_frame, mirror_z=bottom, hold_frames=hold_frames)
    return {"depth": np.asarray(rec["depth"][:n_frames]), "force": np.asarray(rec["force"][:n_frames]),
            "held": np.asarray(rec["force"][n_frames:]), "pole_gap": np.asarray(rec["pole_gap"]),
            "seconds": time.perf_counter() - t0,
            "substeps": int(sum(rec["substeps"][:n_frames]))}


def uniaxial_case(contact: str, nu: float, cells_across: int, strain: float = 0.01, L: float = 0.04,
                  E: float = 1.0e5, load_transits: float = 20.0, n_frames: int = 30,
                  model: str = "fixed_corotated") -> dict:
    """Cube of side L (m) between a fixed floor plate and a top plate moving down to the nominal ``strain``
    (frictionless plates, lateral faces free, dx = L / ``cells_across``).

    Returns ``strain`` and ``force`` (N, the top plate's reaction per frame), ``expected`` = E A eps (N) and
    ``error`` at the final strain (mean of the last 4 frames against the mean of their nominal strains), the
    floor plate's ``force_floor`` (surface mode; grid: the bottom slip points'), the mean axial strain of the
    middle third ``strain_mid`` (1 - F_zz), ``seconds``, ``particles`` and the ``solver``."""
    dx = L / cells_across
    h = dx / 2
    g = (np.arange(2 * cells_across) + 0.5) * h - L / 2
    X = np.stack(np.meshgrid(g, g, g + L / 2, indexing="ij"), -1).reshape(-1, 3)
    mat = Material(name="cube", model=model, youngs_modulus=E, poisson_ratio=nu, density=DENSITY)
    cfg = dict(device="cpu", dx=dx, gravity=[0.0, 0.0, 0.0], floor=False, margin_cells=3,
               contact="grid" if contact == "pins" else contact, energy_guard_tolerance=0.0)
    s = MPMSolver(X, h ** 3, mat, config=cfg, label="uniaxial")
    total = load_transits * L / mat.bar_wave_speed()
    half = L / 2 + 2 * dx
    if contact == "grid":
        bottom = _plate_points(half, h, 0.0)
        fixed = DirichletPoints(bottom, np.zeros_like(bottom), np.zeros(len(bottom), int),
                                normals=np.tile([0.0, 0.0, 1.0], (len(bottom), 1)), advect=False)
    elif contact == "pins":  # the bottom layer's surface points held at z = 0 (slip)
        low = X[:, 2] < h
        target = X[low].copy()
        target[:, 2] = 0.0
        fixed = ParticlePins(np.flatnonzero(low), target, np.tile([0.0, 0.0, -1.0], (int(low.sum()), 1)),
                             np.zeros(int(low.sum()), int), slip=True)
    else:
        fixed = Collider("plane", (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), finger_id=0)
    rec: dict[str, list] = {"strain": [], "force": [], "force_floor": [], "strain_mid": []}
    mid = np.abs(X[:, 2] - L / 2) < L / 6

    def on_frame(f, d, st):
        r = np.asarray(st.reaction)
        rec["strain_mid"].append(1.0 - float(s.deformation_gradients()[mid, 2, 2].mean()))
        rec["strain"].append(d / L)
        rec["force"].append(-float(r[1, 2]))
        rec["force_floor"].append(float(r[0, 2]))

    t0 = time.perf_counter()
    _press(s, contact, L, half, strain * L, total, n_frames, on_frame, fixed=fixed)
    seconds = time.perf_counter() - t0
    out = {k: np.asarray(v) for k, v in rec.items()}
    eps = float(frame_mean(out["strain"])[-4:].mean())
    out.update(expected=E * L * L * eps, seconds=seconds, particles=len(X), dx=dx, contact=contact, nu=nu, solver=s)
    out["error"] = float(out["force"][-4:].mean()) / out["expected"] - 1.0
    out["error_floor"] = float(out["force_floor"][-4:].mean()) / out["expected"] - 1.0
    return out


def frame_mean(values: np.ndarray) -> np.ndarray:
    """Frame means of a quantity that starts at 0 and is given at the frame ends (linear within a frame): the
    reactions are frame means, so they belong to these plate travels."""
    d = np.concatenate([[0.0], np.asarray(values, float)])
    return 0.5 * (d[1:] + d[:-1])


def summary_line(res: dict, kind: str, extra: Optional[str] = None) -> str:
    """One printable line of a case's errors."""
    if kind == "hertz":
        errs = " ".join(f"{100 * e:+.0f}%" for e in res["force_error"])
        rad = " ".join(f"{100 * e:+.0f}%" for e in res["radius_error"])
        body = f"force err at {', '.join(f'{1e3 * a:g}' for a in res['at'])} mm: {errs}; radius err: {rad}"
    else:
        body = f"nu={res['nu']:g} force err {100 * res['error']:+.1f}% (floor plate {100 * res['error_floor']:+.1f}%)"
    return (f"{kind:8s} {res['contact']:7s} dx={1e3 * res['dx']:.3g} mm {body}; {res['particles']} particles, "
            f"{res['seconds']:.1f} s" + (f"; {extra}" if extra else ""))


def indentation_case(cells_per_contact_radius: float = 2.7, depth: float = 0.004, R: float = HERTZ_R,
                     E: float = HERTZ_E, nu: float = HERTZ_NU, load_transits: float = 12.0, n_frames: int = 30,
                     depths: tuple[float, ...] = (0.002, 0.003, 0.004)) -> dict:
    """A rigid sphere collider (radius R) indenting an elastic block (Hertz's half-space, approximated by a block
    of 8 contact radii a = sqrt(R depth) across and 5 deep on a frictionless plane collider) by ``depth`` (m);
    dx = a / ``cells_per_contact_radius``.  Returns ``force_at``, ``hertz_at`` (N) and ``force_error`` at
    ``depths`` (m), ``seconds``, ``particles``."""
    a = float(np.sqrt(R * depth))
    dx = a / cells_per_contact_radius
    h = dx / 2
    half, deep = 4 * a, 5 * a
    n_xy, n_z = int(round(2 * half / h)), int(round(deep / h))
    g = (np.arange(n_xy) + 0.5) * h - half
    X = np.stack(np.meshgrid(g, g, (np.arange(n_z) + 0.5) * h, indexing="ij"), -1).reshape(-1, 3)
    mat = Material(name="block", model="fixed_corotated", youngs_modulus=E, poisson_ratio=nu, density=DENSITY)
    s = MPMSolver(X, h ** 3, mat, config=dict(device="cpu", dx=dx, gravity=[0.0, 0.0, 0.0], floor=False,
                                              margin_cells=3, energy_guard_tolerance=0.0), label="indentation")
    base = Collider("plane", (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), finger_id=0)
    total = load_transits * deep / mat.bar_wave_speed()
    fdt = total / n_frames
    centre = deep + R
    rec: dict[str, list] = {"depth": [], "force": []}
    t0 = time.perf_counter()
    for f in range(n_frames):
        vz = -_ramped_speed((f + 0.5) * fdt, total, depth)
        ball = Collider("sphere", (0.0, 0.0, centre), radius=R, velocity=(0.0, 0.0, vz), finger_id=1)
        st = s.step_frame(fdt, colliders=[base, ball])
        centre += vz * fdt
        rec["depth"].append(deep + R - centre)
        rec["force"].append(-float(np.asarray(st.reaction)[1, 2]))
    out = {k: np.asarray(v) for k, v in rec.items()}
    at = np.asarray(depths, float)
    out.update(at=at, seconds=time.perf_counter() - t0, particles=len(X), dx=dx)
    out["force_at"] = np.interp(at, frame_mean(out["depth"]), out["force"])
    out["hertz_at"] = hertz_force(at, R, E, nu)
    out["force_error"] = out["force_at"] / out["hertz_at"] - 1.0
    return out


# ----------------------------------------------------------------------------------------------- collider fingers
def block_particles(half: float, deep: float, h: float) -> np.ndarray:
    """Particles (spacing h, m) filling [-half, half]^2 x [0, deep] (m), cell-centred: (N, 3)."""
    g = (np.arange(int(round(2 * half / h))) + 0.5) * h - half
    z = (np.arange(int(round(deep / h))) + 0.5) * h
    return np.stack(np.meshgrid(g, g, z, indexing="ij"), -1).reshape(-1, 3)


def force_ramp(n: int, ramp: float = 0.2) -> np.ndarray:
    """Force coefficients 0 .. 1 over n frames (1): constant rate after an accelerating first ``ramp`` fraction."""
    u = np.linspace(0.0, 1.0, n)
    return np.where(u < ramp, u * u / (2 * ramp), u - ramp / 2) / (1 - ramp / 2)


def finger_field(surface: np.ndarray, centres: np.ndarray, normals: np.ndarray, c: np.ndarray, eta: float,
                 sigma: float) -> tuple[dict, dict]:
    """The eq. 3 field (:func:`tasks.control.dirichlet_field.dirichlet_field`, support 2.5 sigma) and the contact
    patches of fixed round patches (radius ``sigma``, m) of the first fingers at ``centres`` (finger, xyz) m with
    outward unit ``normals``, over the surface points ``surface`` (point, xyz) m, force coefficients ``c`` (frame,
    finger) and ``eta`` (m per unit coefficient); the other fingers are inactive.  Returns (field, patches)."""
    T, k = c.shape
    def pad(a, fill=0.0):  # the remaining fingers
        return np.concatenate([a, np.full((T, N_FINGERS - k) + a.shape[2:], fill)], axis=1)
    C = pad(np.broadcast_to(centres, (T, k, 3)).copy())
    N = pad(np.broadcast_to(normals, (T, k, 3)).copy())
    N[:, k:, 2] = 1.0
    axes = np.zeros((T, N_FINGERS, 2, 3))
    for i in range(N_FINGERS):
        u = np.cross(N[0, i], [1.0, 0.0, 0.0] if abs(N[0, i, 0]) < 0.9 else [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
        axes[:, i] = [u, np.cross(N[0, i], u)]
    radii, active = pad(np.full((T, k, 2), sigma)), pad(c > 0, False).astype(bool)
    patches = {"patch_centers": C, "patch_normals": N, "patch_axes": axes, "patch_radii": radii,
               "patch_active": active}
    field = dirichlet_field(surface, C, N, axes, radii, active, pad(c), {"eta": eta, "support": 2.5,
                                                                       "min_weight": 0.05})
    return {name: a.data for name, a in field.items()}, patches


def press_fingers(solver: MPMSolver, surface: np.ndarray, field: dict, patches: dict, frame_dt: float,
                  fixed: Optional[Collider] = None) -> tuple[np.ndarray, np.ndarray]:
    """Step one frame (``frame_dt`` s) per frame of the field after the first with the collider fingers of
    :func:`tasks.physics.rollout_fingers.finger_colliders` (and the static collider ``fixed``).  Returns per frame the
    reactions (frame, finger, xyz) N and the momentum at its end (frame, xyz) kg m/s."""
    torn = np.zeros(len(surface), bool)
    reactions, momenta = [], []
    for f in range(1, len(field["weight"])):
        tips = finger_colliders(solver, surface, field, patches, f, torn, frame_dt)
        st = solver.step_frame(frame_dt, colliders=tips + ([fixed] if fixed is not None else []))
        reactions.append(np.asarray(st.reaction)[:N_FINGERS])
        momenta.append(np.asarray(st.momentum, float))
    return np.array(reactions), np.array(momenta)


def fingertip_case(cells_per_contact_radius: float = 1.5, depth: float = 0.002, E: float = HERTZ_E,
                   nu: float = HERTZ_NU, c_of_frame: Optional[np.ndarray] = None, load_transits: float = 12.0,
                   depths: tuple[float, ...] = (0.001, 0.0015, 0.002)) -> dict:
    """A collider finger (sphere of the fingertip pad radius R) driven by the eq. 3 field into an elastic block
    (Hertz's half-space: 8 contact radii a = sqrt(R depth) across, 5 deep, on a frictionless plane collider):
    one patch (sigma = 2 a) on the top face's centre, eta = ``depth`` (m), force coefficients ``c_of_frame``
    (default :func:`force_ramp` over 31 frames) over ``load_transits`` bar-wave transits of the block's depth;
    dx = a / ``cells_per_contact_radius``.  Returns ``travel`` (frame,) m (the field's amplitude), ``reaction``
    (frame - 1, finger, xyz) N, at ``depths``: ``at``, ``force_at``, ``hertz_at`` (N), ``force_error``;
    ``seconds``, ``particles``, ``dx``."""
    c = force_ramp(31) if c_of_frame is None else np.asarray(c_of_frame, float)
    R = FINGERTIP_PAD_RADIUS
    a = float(np.sqrt(R * depth))
    dx = a / cells_per_contact_radius
    h = dx / 2
    X = block_particles(4 * a, 5 * a, h)
    deep = X[:, 2].max() + h / 2
    top = X[X[:, 2] > deep - h] + [0.0, 0.0, h / 2]  # the top face's surface points
    field, patches = finger_field(top, np.array([[0.0, 0.0, deep]]), np.array([[0.0, 0.0, 1.0]]), c[:, None],
                                  eta=depth, sigma=2 * a)
    mat = Material(name="block", model="fixed_corotated", youngs_modulus=E, poisson_ratio=nu, density=DENSITY)
    s = MPMSolver(X, h ** 3, mat, config=dict(device="cpu", dx=dx, gravity=[0.0, 0.0, 0.0], floor=False,
                                              margin_cells=3, energy_guard_tolerance=0.0), label="fingertip")
    frame_dt = load_transits * (5 * a) / mat.bar_wave_speed() / (len(c) - 1)
    t0 = time.perf_counter()
    reaction, _ = press_fingers(s, top, field, patches, frame_dt,
                                Collider("plane", (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), finger_id=N_FINGERS - 1))
    travel = np.array([fingertip_travel(field, f)[0] for f in range(len(c))])
    at = np.asarray(depths, float)
    out = {"travel": travel, "reaction": reaction, "at": at, "seconds": time.perf_counter() - t0,
           "particles": len(X), "dx": dx}
    out["force_at"] = np.interp(at, frame_mean(travel[1:]), -reaction[:, 0, 2])
    out["hertz_at"] = hertz_force(at, R, E, nu)
    out["force_error"] = out["force_at"] / out["hertz_at"] - 1.0
    return out
