"""Finger-mapped displacement field and Dirichlet constraints (paper sec. 3.1, eq. 3).

    Delta x(x) = sum_k eta c_k,t phi_k(x) d_k                                                        (eq. 3)

* ``eta`` (m per unit force coefficient, ``cfg.eta``) is the global scaling factor, ``c_k,t`` (1) the force
  coefficient of eq. 1.
* ``d_k = -n_k`` is the squeeze direction of patch k: the INWARD surface normal at the patch centre (the
  contact stage stores outward normals; the paper's ``n_k`` is "the patch normal, i.e. squeezing direction").
* ``phi_k`` (1) is the anisotropic soft weight of the patch of eq. 2::

      phi_k(x) = exp(-q / 2)  if q <= support^2 else 0,    q = (u1/sigma1)^2 + (u2/sigma2)^2 + (h/sigma_n)^2

  with ``r = x - centre_k``, ``u_i = r^T axis_i`` the tangent-plane coordinates along the patch axes (m),
  ``h = r^T n_k`` the normal offset (m) and ``sigma_n = min(sigma1, sigma2)``, so ``phi_k = 1`` at the centre.
  The normal term keeps the far side of an object thicker than ~sigma_n out of the patch.  When
  ``surface_normals`` are given, points whose outward normal faces away from the patch (``n(x)^T n_k <= 0``,
  the inner face of a thin wall, the far side of a thin plate) get ``phi_k = 0`` as well: a finger pushes only
  the surface that faces it.
* Only active patches contribute.  ``weight = max_k phi_k``; a point is constrained when
  ``weight >= cfg.min_weight`` (and ``weight > 0``: a point no patch reaches is never pinned, even with
  ``min_weight <= 0``); the displacement of unconstrained points is stored as 0 (they are free in the MPM)
  and their ``finger`` is -1.
* Superposition: overlapping patches add (eq. 3 is a sum); ``finger`` names the dominant one.

Limitation: the cut at ``support`` sigmas is a hard cut (at the default 2.5 sigma the weight jumps from
exp(-3.125) = 0.044 to 0, below the default ``min_weight`` 0.05, so the Dirichlet set never sees it).
"""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from tasks.core.artifacts import Array, as_numpy, config_value
from tasks.core.step import artifact_step


def patch_weight(points, center, normal, axes, radii, support: float, point_normals=None) -> np.ndarray:
    """Anisotropic soft weight phi_k (1) of one patch at ``points`` (..., 3); see the module doc (eq. 3).

    ``center`` (3,) m, ``normal`` (3,) outward unit, ``axes`` (2, 3) unit tangents, ``radii`` (2,) m.
    """
    r = as_numpy(points) - as_numpy(center)
    axes = as_numpy(axes)
    radii = as_numpy(radii)
    normal = as_numpy(normal)
    q = (r @ axes[0] / radii[0]) ** 2 + (r @ axes[1] / radii[1]) ** 2 + (r @ normal / radii.min()) ** 2
    phi = np.where(q <= support ** 2, np.exp(-0.5 * q), 0.0)
    if point_normals is not None:
        phi = np.where(as_numpy(point_normals) @ normal > 0.0, phi, 0.0)
    return phi


def dirichlet_field(
    surface_points,
    patch_centers,
    patch_normals,
    patch_axes,
    patch_radii,
    patch_active,
    force_coefficients,
    cfg: Any,
    *,
    surface_normals=None,
) -> dict[str, Array]:
    """Target displacement of every surface point per frame (eq. 3) and its Dirichlet mask.

    Args:
        surface_points: (S, 3) m, rest positions of the surface samples.
        patch_centers: (T, F, 3) m; patch_normals: (T, F, 3) outward unit; patch_axes: (T, F, 2, 3) unit;
        patch_radii: (T, F, 2) m; patch_active: (T, F) bool  (the output of :func:`contact_patches`).
        force_coefficients: (T, F) 1, c_k,t.
        cfg: DisplacementConfig-like (eta m, support in sigmas, min_weight 1).
        surface_normals: optional (S, 3) outward normals; enables the facing test of the module doc.

    Returns (float32 storage):
        ``displacement`` (frame, point, xyz) m, zero where unconstrained; ``weight`` (frame, point) 1 =
        max_k phi_k; ``constrained`` (frame, point) bool = weight >= min_weight; ``finger`` (frame, point) int8
        = argmax_k phi_k on constrained points, else -1; ``surface_points`` (point, xyz) m, the rest positions
        (so :func:`constrained_points` can build targets from the field alone); ``amplitude`` (frame, finger) m =
        eta c_k,t of each contributing (active) patch, 0 for the others: the travel of the patch centre along d_k,
        which collider fingertips follow (:func:`tasks.physics.rollout_fingers.fingertip_travel`).
    """
    X = as_numpy(surface_points)
    C = as_numpy(patch_centers)
    Nn = as_numpy(patch_normals)
    U = as_numpy(patch_axes)
    R = as_numpy(patch_radii)
    act = np.asarray(patch_active.data if isinstance(patch_active, Array) else patch_active, dtype=bool)
    c = as_numpy(force_coefficients)
    eta = float(config_value(cfg, "eta"))
    support = float(config_value(cfg, "support"))
    min_weight = float(config_value(cfg, "min_weight"))
    if X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f"surface_points must be (S, 3), got {X.shape}")
    T, F = c.shape
    for name, arr, shape in (("patch_centers", C, (T, F, 3)), ("patch_normals", Nn, (T, F, 3)),
                             ("patch_axes", U, (T, F, 2, 3)), ("patch_radii", R, (T, F, 2)),
                             ("patch_active", act, (T, F))):
        if arr.shape != shape:
            raise ValueError(f"{name} must have shape {shape}, got {arr.shape}")
    Xn = None
    if surface_normals is not None:
        Xn = as_numpy(surface_normals)
        if Xn.shape != X.shape:
            raise ValueError(f"surface_normals must have shape {X.shape}, got {Xn.shape}")
    S = X.shape[0]

    disp = np.zeros((T, S, 3))
    weight = np.zeros((T, S))
    finger = np.full((T, S), -1, dtype=np.int8)
    use = act & (R.min(axis=-1) > 0.0) & np.all(np.isfinite(R), axis=-1)
    safe_R = np.where(use[..., None], R, 1.0)
    # per patch: rows u1, u2, n of its local frame (T, F, 3, 3) and the scales sigma1, sigma2, sigma_n (T, F, 3)
    frame_axes = np.concatenate([U, Nn[:, :, None, :]], axis=2)
    scale = np.concatenate([safe_R, safe_R.min(axis=-1, keepdims=True)], axis=-1)
    offset = np.einsum("tkac,tkc->tka", frame_axes, C)
    chunk = max(1, int(1_500_000 // max(S * F, 1)))
    for lo in range(0, T, chunk):
        sl = slice(lo, min(T, lo + chunk))
        n_t = sl.stop - sl.start
        # local coordinates (u1, u2, h) / (sigma1, sigma2, sigma_n) of every point for every patch: (t, F, 3, S)
        local = (frame_axes[sl].reshape(-1, 3) @ X.T).reshape(n_t, F, 3, S)
        local -= offset[sl][..., None]
        local /= scale[sl][..., None]
        q = np.einsum("tkas,tkas->tks", local, local)
        phi = np.where((q <= support ** 2) & use[sl][..., None], np.exp(-0.5 * q), 0.0)  # (t, F, S)
        if Xn is not None:
            phi *= np.einsum("sc,tkc->tks", Xn, Nn[sl]) > 0.0
        disp[sl] = np.einsum("tks,tk,tkc->tsc", phi, -eta * c[sl], Nn[sl])
        weight[sl] = phi.max(axis=1)
        finger[sl] = np.where(weight[sl] > 0.0, phi.argmax(axis=1), -1)
    weight = weight.astype(np.float32)
    # the mask is taken on the stored (float32) weight so that it reproduces exactly from the artifact; a point
    # that no patch reaches (weight 0) is never a Dirichlet point, even with min_weight <= 0
    constrained = (weight >= np.float32(min_weight)) & (weight > 0)
    disp[~constrained] = 0.0
    finger[~constrained] = -1
    amplitude = np.where(use, eta * c, 0.0)
    return {
        "displacement": Array(disp.astype(np.float32), ("frame", "point", "xyz"), "m",
                              "target displacement of each surface point (eq. 3); 0 where unconstrained"),
        "weight": Array(weight, ("frame", "point"), "1", "max_k phi_k (anisotropic soft weight)"),
        "constrained": Array(constrained, ("frame", "point"), "1", "weight >= min_weight (and > 0): Dirichlet point"),
        "finger": Array(finger, ("frame", "point"), "1", "argmax_k phi_k on constrained points, else -1"),
        "surface_points": Array(X.astype(np.float32), ("point", "xyz"), "m", "rest positions of the surface samples"),
        "amplitude": Array(amplitude.astype(np.float32), ("frame", "finger"), "m",
                           "eta c_k,t of each active patch (its centre's travel along d_k), 0 for an inactive one"),
    }


def constrained_points(field: Mapping[str, Any], frame: int, surface_points=None) -> tuple[np.ndarray, np.ndarray]:
    """Indices (n,) int64 and target positions x + Delta x (n, 3) m of the constrained points of one frame.

    ``field`` is the mapping returned by :func:`dirichlet_field` (values :class:`Array` or numpy arrays, e.g.
    a loaded artifact's ``arrays``); ``surface_points`` (S, 3) m overrides the rest positions stored in it.
    """
    def get(name: str) -> np.ndarray:
        v = field[name]
        return v.data if isinstance(v, Array) else np.asarray(v)

    mask = np.asarray(get("constrained")[frame], dtype=bool)
    idx = np.flatnonzero(mask).astype(np.int64)
    X = as_numpy(surface_points) if surface_points is not None else as_numpy(get("surface_points"))
    targets = X[idx] + as_numpy(get("displacement")[frame][idx])
    return idx, targets


@artifact_step("dirichlet_field", inputs=("object_model", "contact_patches", "force_coefficients"),
               reads=("control.displacement", "object.eta"),
               outputs=("displacement", "weight", "constrained", "finger", "surface_points", "amplitude"))
def dirichlet_field_step(inputs, params):
    """Eq. 3: target displacement of the surface points, the Dirichlet data of the MPM.  The object's own ``eta``
    (m per unit force coefficient) wins over ``control.displacement.eta`` when set."""
    obj, patches = inputs["object_model"], inputs["contact_patches"]
    displacement = dict(params["control.displacement"])
    if params["object.eta"] is not None:
        displacement["eta"] = params["object.eta"]
    out = dirichlet_field(obj["surface_points"], patches["patch_centers"], patches["patch_normals"],
                          patches["patch_axes"], patches["patch_radii"], patches["patch_active"],
                          inputs["force_coefficients"]["force_coefficients"], displacement,
                          surface_normals=obj["surface_normals"])
    peak = np.linalg.norm(out["displacement"].data, axis=-1).max(initial=0.0)
    attrs = {"peak_displacement_m": float(peak)}
    warning = nothing_squeezed(out, patches["patch_active"], inputs["force_coefficients"]["force_coefficients"])
    if warning:  # shown in the task's progress line and the report (flows.runtime.RunTable)
        attrs["warning"] = warning
    return out, attrs


class FieldError(ValueError):
    """The displacement field is unusable (not finite); the message names the likely cause."""


def nothing_squeezed(field: Mapping[str, Array], patch_active: Any, force_coefficients: Any) -> str:
    """Why the field of eq. 3 squeezes nothing ("" when it squeezes): no finger flexes past beta, no patch is
    active, no point passes ``min_weight`` or eta is 0.  A non-finite field raises :class:`FieldError`: the run
    must not simulate it."""
    disp = field["displacement"].data
    if not np.isfinite(disp).all():
        bad = int((~np.isfinite(disp)).any(axis=-1).sum())
        raise FieldError(f"the displacement field is not finite at {bad} point-frames: a config value is out of range "
                         f"(control.displacement.eta or object.eta, control.contact.sigma_min/sigma_max)")
    if np.any(disp):
        return ""
    c = as_numpy(force_coefficients)
    if not np.any(c > 0):
        return ("nothing was squeezed: no finger flexes past control.force.beta (every force coefficient is 0); "
                "check the recording's flexion scale (0..1 or 0..10000) or lower control.force.beta")
    if not np.any(np.asarray(patch_active, dtype=bool)):
        return ("nothing was squeezed: no finger reaches the object (no contact patch is active); check the "
                "fingertip positions' units and frame (metres, object centred at the origin) or the object's size")
    if not np.any(field["constrained"].data):
        return ("nothing was squeezed: no surface point has a patch weight above control.displacement.min_weight; "
                "lower it")
    return "nothing was squeezed: the displacement field is zero; control.displacement.eta (or object.eta) is 0"
