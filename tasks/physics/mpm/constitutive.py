"""Constitutive models as Warp functions (paper eqs. 4-5).

Every model provides
  * the Kirchhoff stress  tau = J sigma = dPsi/dF_E F_E^T   (eq. 4; the Cauchy stress is tau / J), and
  * the return mapping    F_E <- psi(F_E)                   (eq. 5), applied after F_E <- (I + dt grad v) F_E,
  * the elastic energy density Psi(F_E) per unit reference volume (energy statistics).

MLS-MPM needs the Kirchhoff stress: the nodal force is f_i = -sum_p V_p^0 tau_p grad w_ip, because
V_p sigma_p = V_p^0 J_p sigma_p = V_p^0 tau_p.

Conventions
-----------
* Hencky strain eps = log(Sigma) (principal, signed singular values clamped to >= 1e-4).
* Von Mises: the yield stress tau_y is the UNIAXIAL yield stress.  The criterion on the Kirchhoff stress is
  sqrt(3/2) |dev tau| <= tau_y, i.e. |dev eps| <= sqrt(2/3) tau_y / (2 mu).  Check (uniaxial stress s):
  dev tau = s (-1/3, -1/3, 2/3), |dev tau| = s sqrt(2/3), so sqrt(3/2) |dev tau| = s: yield at s = tau_y.
  (Dropping the sqrt(2/3) factor - a defect found in public code - yields at sqrt(3/2) tau_y.)
* Linear hardening: tau_y(alpha) = tau_y + H alpha, alpha = equivalent plastic strain = sqrt(2/3) |eps_p|
  (equal to the axial plastic strain in a uniaxial test).  Radial return with the consistency condition:
  dgamma = (|dev eps| - r(alpha)) / (1 + H / (3 mu)), alpha += sqrt(2/3) dgamma.
* Foam (viscoplastic): as above with Perzyna regularisation: dgamma_visc = dgamma / (1 + t_v / dt),
  t_v = viscosity / (2 mu) (viscosity 0 = rate independent), plus a volumetric cap: tr(eps) is clamped
  from below at -crush_strain (the excess compression stays as permanent plastic compaction) and from above at
  dilation_strain (the excess expansion stays as permanent plastic dilation: the material tore open), as the
  snow model's critical compression and stretch (Stomakhin et al. 2013) but on the volume only.
* Fluid: Tait pressure p = K / gamma (J^-gamma - 1) and Newtonian viscosity; the Kirchhoff stress is
  tau = -J p I + J mu_v (grad v + grad v^T - 2/3 div v I); F_E is reset to min(J, 1)^(1/3) I (shear memory
  removed).  No tension: J is capped at 1, so p >= 0 - a free liquid separates (cavitates, breaks into drops)
  instead of pulling back on what it leaves, and a spray's volume does not grow without bound.
* Fixed-corotated uses the polar rotation R of F (closest proper rotation, det R = +1, the same R as the
  rotation-variant SVD U V^T).  It is tracked per particle as a quaternion, warm-started from the previous
  substep and refined by a Newton step on SO(3) (:func:`polar_rotation_quat`; the gradient-only step of
  Mueller et al. 2016 recovers only ~2/3 of each increment and lags), instead of a 3x3 SVD per substep.
* The StVK-Hencky models (von Mises, foam) likewise track the eigenbasis of b = F F^T per particle (same quaternion
  array) and return-map in it (:func:`hencky_plastic_return_warm`: one Jacobi sweep per substep is typical) instead
  of a cold 3x3 SVD per substep, which cost ~0.5 us, 3/4 of a plastic particle's substep on one CPU core; the SVD
  path (:func:`hencky_plastic_return`) remains for an inverted trial F.
"""
from __future__ import annotations

import warp as wp

from .materials import MODEL_CODES

wp.set_module_options({"enable_backward": False})

# material model codes as compile-time constants (the kernels branch on them; see materials.MODEL_CODES)
MODEL_FIXED_COROTATED = wp.constant(MODEL_CODES["fixed_corotated"])
MODEL_NEO_HOOKEAN = wp.constant(MODEL_CODES["neo_hookean"])
MODEL_VON_MISES = wp.constant(MODEL_CODES["von_mises"])
MODEL_FOAM = wp.constant(MODEL_CODES["foam"])
MODEL_FLUID = wp.constant(MODEL_CODES["fluid"])

SQRT_2_3 = wp.constant(0.816496580927726)  # sqrt(2/3)
MIN_SIGMA = wp.constant(1.0e-4)
MIN_J = wp.constant(1.0e-6)
EIGEN_MAX_SWEEPS = wp.constant(8)  # Jacobi sweeps of sym_eigen_warm (a cold start needs 3-4)
# off-diagonal / diagonal norm at which sym_eigen_warm stops: the stress then misses at most
# mu sqrt(3) EIGEN_TOL (d_max / d_min) off its diagonal (tests/physics/test_mpm_closed_forms.py).  1e-5, not 1e-6
# (near float32 resolution, a second sweep for ~half the foam): -5 % on the plush toy's particle kernel, its rollouts
# within 8e-6 m and Table 2 within 0.0034 but for one ranking cell (docs/results/presets.md, "Eigen-solve tolerance")
EIGEN_TOL = wp.constant(1.0e-5)
MEMBRANE_NEWTON = wp.constant(5)  # Newton steps of membrane_stretch_neo_hookean (float32 converged by 3 at A in [0.3, 3])
MEMBRANE_PLASTIC_ITERS = wp.constant(6)  # secant steps of membrane_plastic_return (at most; most stop after 1-3)
MEMBRANE_PLASTIC_TOL = wp.constant(1.0e-6)  # |n . tau n| / (lambda + 2 mu) at which membrane_plastic_return stops


# --------------------------------------------------------------------------------------------- helpers
@wp.func
def col(A: wp.mat33, j: int) -> wp.vec3:
    """Column j of A, built element by element (never through a matrix constructor)."""
    return wp.vec3(A[0, j], A[1, j], A[2, j])


@wp.func
def polar_rotation_quat(A: wp.mat33, q0: wp.quat, max_iter: int, tol: float) -> wp.quat:
    """Rotation part of A (maximiser of tr(R^T A) over SO(3)), tracked as a unit quaternion.

    Newton iteration on the rotation manifold, warm-started from the particle's previous rotation: with
    B = R^T A, the objective tr(R^T A) around R exp([w]) is tr B + g.w - 1/2 w^T H w, with
    g = (B32 - B23, B13 - B31, B21 - B12) and H = tr(B) I - sym(B), so w = H^-1 g (body frame) and
    R <- R exp([w]).  Quadratic convergence: one iteration per substep tracks the rotation to O(dt^2).
    When H is not positive definite (far from the optimum, e.g. a cold start on a large rotation) the step
    falls back to the gradient step w = g / |tr B| of Mueller et al. 2016, which always ascends.

    A step below ``tol`` (rad) ends the iteration but is still taken: discarded, as it was before, every substep's
    rotation increment below tol was lost, so under a slow load R lagged F's rotation by up to tol for good and the
    stress 2 mu (F - R) F^T kept a skew part 2 mu tol, a torque no energy pays for (a cantilever of the plane-stress
    wall under its weight, 2 mu tol = 67 Pa against its 63 kPa bending stress, crept on: 0.92 -> 1.75x its
    Euler-Bernoulli sag over 0.25 -> 1.5 s; with the step taken its ringing died out near 1.10x, and the creep that
    went on from there was the thin walls' zero-energy modes, :func:`wall_normal_psi`)."""
    q = q0
    for _it in range(max_iter):
        R = wp.quat_to_matrix(q)
        B = wp.transpose(R) @ A
        g = wp.vec3(B[2, 1] - B[1, 2], B[0, 2] - B[2, 0], B[1, 0] - B[0, 1])
        tr = B[0, 0] + B[1, 1] + B[2, 2]
        h00 = tr - B[0, 0]
        h11 = tr - B[1, 1]
        h22 = tr - B[2, 2]
        h01 = -0.5 * (B[0, 1] + B[1, 0])
        h02 = -0.5 * (B[0, 2] + B[2, 0])
        h12 = -0.5 * (B[1, 2] + B[2, 1])
        # cofactors of the symmetric H (Sylvester test for positive definiteness + explicit inverse)
        c00 = h11 * h22 - h12 * h12
        c01 = h02 * h12 - h01 * h22
        c02 = h01 * h12 - h02 * h11
        det = h00 * c00 + h01 * c01 + h02 * c02
        w = wp.vec3(0.0)
        if h00 > 0.0 and h00 * h11 - h01 * h01 > 0.0 and det > 1.0e-12 * tr * tr * tr:
            c11 = h00 * h22 - h02 * h02
            c12 = h01 * h02 - h00 * h12
            c22 = h00 * h11 - h01 * h01
            w = wp.vec3(
                c00 * g[0] + c01 * g[1] + c02 * g[2],
                c01 * g[0] + c11 * g[1] + c12 * g[2],
                c02 * g[0] + c12 * g[1] + c22 * g[2],
            ) / det
        else:
            w = g / (wp.abs(tr) + 1.0e-20)
        w2 = wp.dot(w, w)
        if w2 > 1.0:
            w = w / wp.sqrt(w2)  # trust region: at most 1 rad per iteration
        # q <- q * exp(w/2) (body-frame increment), exp approximated by normalise(w/2, 1)
        dq = wp.quat(0.5 * w[0], 0.5 * w[1], 0.5 * w[2], 1.0)
        q = wp.normalize(q * dq)
        if w2 < tol * tol:  # converged: the step just taken was below tol (taken all the same, see the doc)
            break
    return q


@wp.func
def polar_track_quat(A: wp.mat33, q0: wp.quat, iters: int) -> wp.quat:
    """Cheap per-substep tracking of the rotation of A from the previous substep's rotation ``q0``.

    Scaled gradient step (world frame): w = 1.5 sum_j r_j x a_j / tr(R^T A), R <- exp([w]) R.  The factor 1.5 is
    the exact Newton step for an isotropic stretch (H = tr(B) I - sym(B) = 2/3 tr(B) I when B = s I); for a
    stretch with principal strains eps the step error is O(eps) times the rotation increment, so the tracked
    rotation lags the exact one by O(eps |w| dt) only (Mueller et al.'s unscaled step recovers 2/3 of every
    increment and lags by half an increment).  Frames start and end with the full Newton iteration
    :func:`polar_rotation_quat`, which removes any residual.
    """
    q = q0
    for _it in range(iters):
        R = wp.quat_to_matrix(q)
        r0 = wp.vec3(R[0, 0], R[1, 0], R[2, 0])
        r1 = wp.vec3(R[0, 1], R[1, 1], R[2, 1])
        r2 = wp.vec3(R[0, 2], R[1, 2], R[2, 2])
        a0 = wp.vec3(A[0, 0], A[1, 0], A[2, 0])
        a1 = wp.vec3(A[0, 1], A[1, 1], A[2, 1])
        a2 = wp.vec3(A[0, 2], A[1, 2], A[2, 2])
        tr = wp.dot(r0, a0) + wp.dot(r1, a1) + wp.dot(r2, a2)
        w = (wp.cross(r0, a0) + wp.cross(r1, a1) + wp.cross(r2, a2)) * (1.5 / (wp.abs(tr) + 1.0e-20))
        w2 = wp.dot(w, w)
        if w2 > 1.0:
            w = w / wp.sqrt(w2)
        q = wp.normalize(wp.quat(0.5 * w[0], 0.5 * w[1], 0.5 * w[2], 1.0) * q)
    return q


@wp.func
def diag3(a: float, b: float, c: float) -> wp.mat33:
    return wp.mat33(a, 0.0, 0.0, 0.0, b, 0.0, 0.0, 0.0, c)


@wp.func
def safe_log(s: float) -> float:
    return wp.log(wp.max(s, MIN_SIGMA))


# --------------------------------------------------------------------------------------------- fixed corotated
@wp.func
def tau_fixed_corotated(F: wp.mat33, R: wp.mat33, mu: float, lam: float) -> wp.mat33:
    """Kirchhoff stress of fixed-corotated elasticity: 2 mu (F - R) F^T + lambda (J - 1) J I."""
    J = wp.determinant(F)
    return 2.0 * mu * (F - R) @ wp.transpose(F) + wp.identity(n=3, dtype=float) * (lam * (J - 1.0) * J)


@wp.func
def psi_fixed_corotated(F: wp.mat33, R: wp.mat33, mu: float, lam: float) -> float:
    D = F - R
    J = wp.determinant(F)
    return mu * wp.ddot(D, D) + 0.5 * lam * (J - 1.0) * (J - 1.0)


# --------------------------------------------------------------------------------------------- neo-Hookean
@wp.func
def tau_neo_hookean(F: wp.mat33, mu: float, lam: float) -> wp.mat33:
    """Kirchhoff stress of compressible Neo-Hookean: mu (F F^T - I) + lambda ln(J) I."""
    J = wp.max(wp.determinant(F), MIN_J)
    I = wp.identity(n=3, dtype=float)
    return mu * (F @ wp.transpose(F) - I) + I * (lam * wp.log(J))


@wp.func
def psi_neo_hookean(F: wp.mat33, mu: float, lam: float) -> float:
    J = wp.max(wp.determinant(F), MIN_J)
    lj = wp.log(J)
    return 0.5 * mu * (wp.ddot(F, F) - 3.0) - mu * lj + 0.5 * lam * lj * lj


# ---------------------------------------------------------------------------------- plane-stress membranes
@wp.func
def area_normal(F: wp.mat33, N: wp.vec3) -> wp.vec3:
    """cof(F) N = det(F) F^-T N (Nanson): the deformed normal of the material plane with unit rest normal N, its
    length the plane's area stretch.  Columns f_i of F: cof(F) = [f2 x f3, f3 x f1, f1 x f2]."""
    f1 = col(F, 0)
    f2 = col(F, 1)
    f3 = col(F, 2)
    return N[0] * wp.cross(f2, f3) + N[1] * wp.cross(f3, f1) + N[2] * wp.cross(f1, f2)


@wp.func
def membrane_stretch_corotated(A: float, r: float, mu: float, lam: float) -> float:
    """Normal stretch g = n . F N of a fixed-corotated membrane at area stretch A with zero normal stress: with
    F^T n = g N, n . tau n = 2 mu (g^2 - g r) + lam (J - 1) J, J = g A, r = n . R N (1 without transverse shear),
    vanishes at g = (2 mu r + lam A) / (2 mu + lam A^2)."""
    return (2.0 * mu * r + lam * A) / (2.0 * mu + lam * A * A)


@wp.func
def membrane_stretch_neo_hookean(A: float, mu: float, lam: float) -> float:
    """Normal stretch g = n . F N of a neo-Hookean membrane at area stretch A with zero normal stress: the root of
    n . tau n = mu (g^2 - 1) + lam ln(g A) (F^T n = g N), in s = ln g: h(s) = mu (e^2s - 1) + lam (s + ln A).  h is
    convex and increasing, so Newton from its linearisation at s = 0, s0 = -lam ln A / (2 mu + lam), converges
    monotonically after its first step.  A step that leaves s unchanged has reached the float32 fixed point, which
    every further step would return again: the loop stops there (the result is the same to the bit)."""
    la = wp.log(A)
    s = -lam * la / (2.0 * mu + lam)
    for _ in range(MEMBRANE_NEWTON):
        e2 = wp.exp(2.0 * s)
        s_next = s - (mu * (e2 - 1.0) + lam * (s + la)) / (2.0 * mu * e2 + lam)
        if s_next == s:
            break
        s = s_next
    return wp.exp(s)


@wp.func
def membrane_F(F: wp.mat33, N: wp.vec3, R: wp.mat33, model: int, mu: float, lam: float) -> wp.mat33:
    """Zero normal stress on a particle of a wall thinner than the grid (a shell's plane-stress condition): keep the in-plane columns
    F T1, F T2 of its wall (unit rest normal N, T1 x T2 = N) and the transverse shear (the part of F N along the
    wall), and set the normal stretch g = n . F N (n the deformed unit normal, :func:`area_normal`) to the value at
    which n . tau n vanishes for the model (fixed-corotated with the rotation R of F, neo-Hookean; mu, lam in Pa):
    F <- F + (g* - g) n N^T.  det F = g A (A the area stretch), so the wall thins as its area grows, as a thin shell
    does, instead of locking its volume (nu -> 0.5) against a grid that holds its thickness; the transverse shear,
    which the grid's smooth field gives a dented thin wall, keeps its stiffness.  A degenerate plane (area
    stretch < 1e-6) is left as it is (the det guard reports it)."""
    m = area_normal(F, N)
    A = wp.length(m)
    if A < 1.0e-6:
        return F
    n = m / A
    g = float(1.0)
    if model == MODEL_NEO_HOOKEAN:
        g = membrane_stretch_neo_hookean(A, mu, lam)
    else:
        g = membrane_stretch_corotated(A, wp.dot(n, R @ N), mu, lam)
    return F + wp.outer((g - wp.dot(n, F @ N)) * n, N)


@wp.func
def wall_normal_psi(F: wp.mat33, Fp: wp.mat33, N: wp.vec3, k: float) -> float:
    """Energy density (J/m^3) of a thin wall's normal stiffness: k / 2 |F N - Fp N|^2, with F the wall particle's
    F_E as its grid deforms it, Fp its plane-stress projection (:func:`membrane_F`, which changes only the normal
    stretch n . F N), N the unit rest normal and k (Pa) = ``mpm.wall_normal_stiffness`` x 2 mu: a penalty on the
    normal stretch's departure from the plane-stress one, which touches neither the in-plane columns nor the
    transverse shear and has no Poisson coupling (no volumetric locking; the plane-stress part of the energy is
    the model's at Fp).  Plane stress alone gives the grid's normal velocity gradient across a wall no stiffness, and
    with two particle layers across the wall the grid then keeps velocity modes that move the particles at no strain
    energy (a clamped strip crept under its weight, a held ball's force crept; docs/limits/thin-walls.md)."""
    d = F @ N - Fp @ N
    return 0.5 * k * wp.dot(d, d)


@wp.func
def wall_normal_tau(F: wp.mat33, Fp: wp.mat33, N: wp.vec3, k: float) -> wp.mat33:
    """Kirchhoff stress (Pa) of :func:`wall_normal_psi` (Fp held): P = k (F N - Fp N) N^T, tau = P F^T = k d a^T with
    d = F N - Fp N (along the deformed normal) and a = F N, symmetrised (d and a are parallel up to the transverse
    shear).  Not the energy's full gradient: Fp moves with F through the area stretch A, and with g = n . F N = J / A,
    (dJ/dF) F^T = J I and (dA/dF) F^T = A (I - n n^T) the exact stress is k (g - g*) [g n n^T + c (I - n n^T)],
    c = -A dg*/dA (nu / (1 - nu) at rest).  Tried (2026-12-04): it is conservative (the rubber duck at
    ``mpm.wall_normal_stiffness`` 1 runs clean where this form trips the energy guard at frame 15), but where the
    grid holds a wall's thickness (g > g* as it stretches) its in-plane term stiffens the stretch: the ball's
    breathing amplitude -2 % -> -9 % of the membrane sphere's (``tests/physics/test_membrane.py``).  This form is kept."""
    a = F @ N
    d = a - Fp @ N
    return 0.5 * k * (wp.outer(d, a) + wp.outer(a, d))


# --------------------------------------------------------------------------------------------- StVK-Hencky
@wp.func
def tau_hencky_principal(eps: wp.vec3, mu: float, lam: float) -> wp.vec3:
    """Principal Kirchhoff stresses of StVK-Hencky: 2 mu eps + lambda tr(eps)."""
    tr = eps[0] + eps[1] + eps[2]
    return 2.0 * mu * eps + wp.vec3(lam * tr, lam * tr, lam * tr)


@wp.func
def hencky_strain(sigma: wp.vec3) -> wp.vec3:
    return wp.vec3(safe_log(sigma[0]), safe_log(sigma[1]), safe_log(sigma[2]))


@wp.func
def tau_hencky(F: wp.mat33, mu: float, lam: float) -> wp.mat33:
    """Kirchhoff stress of StVK-Hencky elasticity, tau = U diag(2 mu eps + lambda tr eps) U^T."""
    U = wp.mat33()
    s = wp.vec3()
    V = wp.mat33()
    wp.svd3(F, U, s, V)
    t = tau_hencky_principal(hencky_strain(s), mu, lam)
    return U @ diag3(t[0], t[1], t[2]) @ wp.transpose(U)


@wp.func
def psi_hencky(F: wp.mat33, mu: float, lam: float) -> float:
    U = wp.mat33()
    s = wp.vec3()
    V = wp.mat33()
    wp.svd3(F, U, s, V)
    e = hencky_strain(s)
    tr = e[0] + e[1] + e[2]
    return mu * wp.dot(e, e) + 0.5 * lam * tr * tr


@wp.struct
class PlasticResult:
    F: wp.mat33  # returned elastic deformation gradient F_E
    tau: wp.mat33  # Kirchhoff stress of the returned F_E
    alpha: float  # updated equivalent plastic strain
    q: wp.quat  # eigenbasis of the trial F_E F_E^T (:func:`hencky_plastic_return_warm`; the warm start otherwise)


@wp.struct
class PrincipalReturn:
    eps: wp.vec3  # returned principal Hencky strains
    alpha: float  # updated equivalent plastic strain
    changed: int  # 1: the return mapping moved the strain (F_E must be rebuilt)


@wp.func
def hencky_return_principal(eps: wp.vec3, mu: float, tau_y: float, hardening: float, alpha: float,
                            viscosity: float, crush: float, dilation: float, is_foam: int,
                            dt: float) -> PrincipalReturn:
    """Return mapping of von Mises / foam on the principal Hencky strains ``eps`` (module doc: volumetric caps of
    the foam, then the radial return with linear hardening and Perzyna viscosity)."""
    res = PrincipalReturn()
    res.alpha = alpha
    res.changed = 0
    if is_foam != 0:
        tr0 = eps[0] + eps[1] + eps[2]
        if tr0 < -crush:
            shift = (-crush - tr0) / 3.0
            eps = eps + wp.vec3(shift, shift, shift)
            res.changed = 1
        elif tr0 > dilation:
            shift = (dilation - tr0) / 3.0
            eps = eps + wp.vec3(shift, shift, shift)
            res.changed = 1
    tr = eps[0] + eps[1] + eps[2]
    mean = tr / 3.0
    dev = eps - wp.vec3(mean, mean, mean)
    dev_norm = wp.length(dev)
    radius = SQRT_2_3 * (tau_y + hardening * alpha) / (2.0 * mu)
    if dev_norm > radius and dev_norm > 1.0e-12:
        dgamma = (dev_norm - radius) / (1.0 + hardening / (3.0 * mu))
        if is_foam != 0 and viscosity > 0.0:
            t_v = viscosity / (2.0 * mu)
            dgamma = dgamma / (1.0 + t_v / dt)
        eps = eps - dev * (dgamma / dev_norm)
        res.alpha = alpha + SQRT_2_3 * dgamma
        res.changed = 1
    res.eps = eps
    return res


@wp.func
def hencky_plastic_return(
    F: wp.mat33,
    mu: float,
    lam: float,
    tau_y: float,
    hardening: float,
    alpha: float,
    viscosity: float,
    crush: float,
    dilation: float,
    is_foam: int,
    dt: float,
) -> PlasticResult:
    """Return mapping of StVK-Hencky + von Mises (``MODEL_VON_MISES``) or the viscoplastic foam (``MODEL_FOAM``,
    ``is_foam`` = 1).

    Works on the signed singular values of the trial F_E (rotation-variant SVD, so inversion keeps its sign),
    returns the projected F_E together with its Kirchhoff stress (the SVD is shared).
    """
    U = wp.mat33()
    s = wp.vec3()
    V = wp.mat33()
    wp.svd3(F, U, s, V)
    pr = hencky_return_principal(hencky_strain(s), mu, tau_y, hardening, alpha, viscosity, crush, dilation, is_foam,
                                 dt)
    eps = pr.eps
    res = PlasticResult()
    res.alpha = pr.alpha
    res.q = wp.quat_identity()
    if pr.changed != 0:
        res.F = U @ diag3(wp.exp(eps[0]), wp.exp(eps[1]), wp.exp(eps[2])) @ wp.transpose(V)
    else:
        res.F = F
    t = tau_hencky_principal(eps, mu, lam)
    res.tau = U @ diag3(t[0], t[1], t[2]) @ wp.transpose(U)
    return res


@wp.func
def jacobi_rotation(app: float, aqq: float, apq: float) -> wp.vec2:
    """(c, s) of the Jacobi rotation G (G_pp = G_qq = c, G_pq = s, G_qp = -s) for which (G^T A G)_pq = 0, with the
    smaller of the two angles (|angle| <= pi/4) (Golub & Van Loan, Matrix Computations, sec. 8.5.2)."""
    if apq == 0.0:
        return wp.vec2(1.0, 0.0)
    theta = (aqq - app) / (2.0 * apq)
    t = wp.sign(theta) / (wp.abs(theta) + wp.sqrt(1.0 + theta * theta))
    c = 1.0 / wp.sqrt(1.0 + t * t)
    return wp.vec2(c, t * c)


@wp.struct
class SymEigen:
    Q: wp.mat33  # eigenvectors (columns), a proper rotation
    d: wp.vec3  # eigenvalues (unsorted)


@wp.func
def sym_eigen_warm(A: wp.mat33, q0: wp.quat, max_sweeps: int, tol: float) -> SymEigen:
    """Eigen-decomposition A = Q diag(d) Q^T of the symmetric A by cyclic Jacobi sweeps started from the rotation q0
    (the previous substep's eigenbasis): A is rotated into that basis, where it is nearly diagonal, and swept until
    its off-diagonal norm is at most ``tol`` times its diagonal norm (one sweep per substep is typical; a cold start
    from the identity needs 3-4, at most ``max_sweeps``)."""
    Q = wp.quat_to_matrix(q0)
    B = wp.transpose(Q) @ A @ Q
    for _sweep in range(max_sweeps):
        off = B[0, 1] * B[0, 1] + B[0, 2] * B[0, 2] + B[1, 2] * B[1, 2]
        if off <= tol * tol * (B[0, 0] * B[0, 0] + B[1, 1] * B[1, 1] + B[2, 2] * B[2, 2]):
            break
        cs = jacobi_rotation(B[0, 0], B[1, 1], B[0, 1])
        G = wp.mat33(cs[0], cs[1], 0.0, -cs[1], cs[0], 0.0, 0.0, 0.0, 1.0)
        B = wp.transpose(G) @ B @ G
        Q = Q @ G
        cs = jacobi_rotation(B[0, 0], B[2, 2], B[0, 2])
        G = wp.mat33(cs[0], 0.0, cs[1], 0.0, 1.0, 0.0, -cs[1], 0.0, cs[0])
        B = wp.transpose(G) @ B @ G
        Q = Q @ G
        cs = jacobi_rotation(B[1, 1], B[2, 2], B[1, 2])
        G = wp.mat33(1.0, 0.0, 0.0, 0.0, cs[0], cs[1], 0.0, -cs[1], cs[0])
        B = wp.transpose(G) @ B @ G
        Q = Q @ G
    e = SymEigen()
    e.Q = Q
    e.d = wp.vec3(B[0, 0], B[1, 1], B[2, 2])
    return e


@wp.func
def hencky_plastic_return_warm(
    F: wp.mat33,
    q0: wp.quat,
    mu: float,
    lam: float,
    tau_y: float,
    hardening: float,
    alpha: float,
    viscosity: float,
    crush: float,
    dilation: float,
    is_foam: int,
    dt: float,
) -> PlasticResult:
    """:func:`hencky_plastic_return` from the eigenbasis of the left Cauchy-Green tensor b = F F^T = U diag(s^2) U^T,
    tracked per particle (``q0``: the previous substep's, returned updated in ``q``) by :func:`sym_eigen_warm`,
    instead of a cold 3x3 SVD per substep (which was 3/4 of the cost of a plastic particle).

    The Hencky strains are 1/2 log(d), d the eigenvalues of b; the stress is U diag(tau_i) U^T as before, and a
    returned state is F_E <- U diag(exp(eps_new - eps)) U^T F (= U diag(exp(eps_new)) V^T: V is not needed).  An
    inverted or nearly singular trial F (det F <= 0 or a singular value below the clamp 1e-4 of :func:`safe_log`),
    where the signed singular values matter, takes the SVD path."""
    b = F @ wp.transpose(F)
    e = sym_eigen_warm(b, q0, EIGEN_MAX_SWEEPS, EIGEN_TOL)
    d = e.d
    if wp.determinant(F) <= 0.0 or wp.min(d) < MIN_SIGMA * MIN_SIGMA:
        res = hencky_plastic_return(F, mu, lam, tau_y, hardening, alpha, viscosity, crush, dilation, is_foam, dt)
        res.q = q0
        return res
    eps0 = wp.vec3(0.5 * wp.log(d[0]), 0.5 * wp.log(d[1]), 0.5 * wp.log(d[2]))
    pr = hencky_return_principal(eps0, mu, tau_y, hardening, alpha, viscosity, crush, dilation, is_foam, dt)
    eps = pr.eps
    U = e.Q
    res = PlasticResult()
    res.alpha = pr.alpha
    res.q = wp.normalize(wp.quat_from_matrix(U))
    if pr.changed != 0:
        res.F = U @ diag3(wp.exp(eps[0] - eps0[0]), wp.exp(eps[1] - eps0[1]), wp.exp(eps[2] - eps0[2])) @ (
            wp.transpose(U) @ F)
    else:
        res.F = F
    t = tau_hencky_principal(eps, mu, lam)
    res.tau = U @ diag3(t[0], t[1], t[2]) @ wp.transpose(U)
    return res


@wp.func
def membrane_plastic_return(
    F: wp.mat33,
    n: wp.vec3,
    q0: wp.quat,
    mu: float,
    lam: float,
    tau_y: float,
    hardening: float,
    alpha: float,
) -> PlasticResult:
    """Plane-stress return mapping of a von Mises particle of a wall thinner than the grid, n the wall's current unit
    normal (tracked by the caller: plastic flow moves F_E's reference configuration, so the rest normal no longer
    tells where the wall lies in it).  The grid does not resolve the wall's thickness, so the trial F_E's stretch
    across the wall is free: with N = F^T n / |F^T n| the wall's normal in F_E's reference (then cof(F) N = A n, A
    the area stretch) and g0 = n . F N, the state is the 3D return (:func:`hencky_plastic_return_warm`) of
    F(s) = F + (e^s - g0) n N^T, which keeps F on the wall's plane, at the s = ln g where the returned stress has no
    normal component, h(s) = n . tau(s) n = 0.  Without it a plastic wall's volume is locked twice: elastically
    (lambda) and plastically (von Mises flow keeps the volume, so a wall that cannot thin cannot stretch either).

    Root of h: from the elastic plane-stress strain s0 = -lam ln A / (lam + 2 mu) (exact for an elastic state
    without transverse shear), secant steps whose slope starts at the elastic dh/ds = lam + 2 mu and is kept within
    [0.9 K, 1.1 (lam + 2 mu)] (K = lam + 2 mu / 3, the slope of a perfectly plastic state), until
    |h| <= MEMBRANE_PLASTIC_TOL (lam + 2 mu), or after MEMBRANE_PLASTIC_ITERS steps the iterate of least |h| (at 30 %
    strain ~0.5 % of states end there, float32 noise, <= 8e-6 (lam + 2 mu) off).  Each step is one warm-started
    eigen-solve; every step's plastic strain is measured from the substep's ``alpha``, so F_E, tau and alpha always
    belong to one s.  A degenerate F (|F^T n| or A < 1e-6) takes the 3D return."""
    Nf = wp.transpose(F) @ n
    g0 = wp.length(Nf)
    A = float(0.0)
    if g0 >= 1.0e-6:
        A = wp.length(area_normal(F, Nf / g0))
    if A < 1.0e-6:
        return hencky_plastic_return_warm(F, q0, mu, lam, tau_y, hardening, alpha, 0.0, 0.0, 0.0, 0, 1.0)
    N = Nf / g0
    k_el = lam + 2.0 * mu
    k_lo = 0.9 * (lam + 2.0 * mu / 3.0)
    k_hi = 1.1 * k_el
    s = -lam * wp.log(A) / k_el
    res = hencky_plastic_return_warm(F + wp.outer((wp.exp(s) - g0) * n, N), q0, mu, lam, tau_y, hardening, alpha,
                                     0.0, 0.0, 0.0, 0, 1.0)
    h = wp.dot(n, res.tau @ n)
    best = res
    best_h = wp.abs(h)
    k = k_el
    for _ in range(MEMBRANE_PLASTIC_ITERS):
        if wp.abs(h) <= MEMBRANE_PLASTIC_TOL * k_el:
            break
        s_new = s - h / k
        res = hencky_plastic_return_warm(F + wp.outer((wp.exp(s_new) - g0) * n, N), res.q, mu, lam, tau_y,
                                         hardening, alpha, 0.0, 0.0, 0.0, 0, 1.0)
        h_new = wp.dot(n, res.tau @ n)
        if wp.abs(h_new) < best_h:
            best = res
            best_h = wp.abs(h_new)
        k = wp.clamp((h_new - h) / (s_new - s), k_lo, k_hi)
        s = s_new
        h = h_new
    return best


# --------------------------------------------------------------------------------------------- fluid
@wp.func
def tait_pressure(J: float, K: float, gamma: float) -> float:
    """Tait equation of state p = K / gamma (J^-gamma - 1) (gamma = 1: p = K (1/J - 1)), no tension (J <= 1)."""
    Jc = wp.clamp(J, MIN_J, 1.0)
    return K / gamma * (wp.pow(Jc, -gamma) - 1.0)


@wp.func
def tau_fluid(J: float, gradv: wp.mat33, K: float, gamma: float, visc: float) -> wp.mat33:
    """Kirchhoff stress of the weakly compressible fluid: -J p I + J mu_v (grad v + grad v^T - 2/3 div v I)."""
    I = wp.identity(n=3, dtype=float)
    p = tait_pressure(J, K, gamma)
    div = gradv[0, 0] + gradv[1, 1] + gradv[2, 2]
    shear = gradv + wp.transpose(gradv) - I * (2.0 / 3.0 * div)
    return I * (-J * p) + shear * (J * visc)


@wp.func
def psi_fluid(J: float, K: float, gamma: float) -> float:
    """Stored energy of the Tait fluid per reference volume: -int_1^J p(j) dj (0 for J >= 1: no tension)."""
    Jc = wp.clamp(J, MIN_J, 1.0)
    if gamma == 1.0:
        integral = wp.log(Jc)
    else:
        integral = (wp.pow(Jc, 1.0 - gamma) - 1.0) / (1.0 - gamma)
    return -K / gamma * (integral - (Jc - 1.0))


@wp.func
def fluid_reset(F: wp.mat33) -> wp.mat33:
    """F_E <- min(J, 1)^(1/3) I (the fluid keeps only its volume change, and never stretches: no tension)."""
    J = wp.clamp(wp.determinant(F), MIN_J, 1.0)
    c = wp.pow(J, 1.0 / 3.0)
    return diag3(c, c, c)
