"""Does the body stay put on the table? (``mpm.table_hold``, docs/limits/table-contact.md, "The hold").

One object's rollout (the pipeline's own scene, :func:`tasks.physics.rollout_scene.build_scene`, and frame loop,
:func:`tasks.physics.mpm_rollout.run_frames`, from its gravity preload) run up to the frame where the eq. 3 field's
predicted squeeze peaks (the force-matched calibration's window, :func:`tasks.physics.force_match.calibration_window`),
plus ``extra`` frames, and measured every frame:

- ``tilt`` (deg): the rotation of the body's vertical, from the best-fit rotation (Kabsch) of its particles (those
  still in the body's velocity field) about their centre of mass, from where they rested after the preload;
- ``slide`` (mm): how far the footprint (the particles resting on the table after the preload,
  :func:`tasks.physics.table_hold.table_footprint`, whatever holds them) moved along the table, its mean horizontal
  displacement; ``lift`` (mm) its mean rise;
- the squeeze strain (max over fingers, 1) against the predicted peak, the contact KE/IE and the substeps.

SI inputs; lengths reported in mm, angles in degrees.
"""
from __future__ import annotations

import math
import time
from typing import Any, Mapping, Optional

import numpy as np

from tasks.physics.force_match import calibration_window
from tasks.physics.mpm.preload import PreloadedState
from tasks.physics.mpm_rollout import run_frames
from tasks.physics.rollout_scene import build_scene, squeeze_regions
from tasks.physics.table_hold import table_footprint


def body_tilt(x0: np.ndarray, x: np.ndarray, mass: np.ndarray) -> float:
    """deg: the angle by which the best-fit rotation of points ``x0`` -> ``x`` (n, 3) m, weights ``mass`` (n,),
    about their centres of mass tips the vertical e_z (Kabsch)."""
    w = mass / mass.sum()
    a, b = x0 - w @ x0, x - w @ x
    u, _, vt = np.linalg.svd((a * w[:, None]).T @ b)
    d = np.sign(np.linalg.det(u @ vt))
    rot = (u @ np.diag([1.0, 1.0, d]) @ vt).T  # x - c = rot (x0 - c0)
    return float(np.degrees(np.arccos(np.clip(rot[2, 2], -1.0, 1.0))))


def hold_case(obj: Mapping[str, np.ndarray], obj_attrs: Mapping[str, Any], field: Mapping[str, np.ndarray],
              forces: np.ndarray, patches: Mapping[str, np.ndarray], times: np.ndarray,
              materials: Mapping[str, Any], mpm: Mapping[str, Any], sim: Mapping[str, Any], boundary: str,
              preloaded: Optional[PreloadedState], extra: int = 3, snapshots: Optional[str] = None) -> dict:
    """One rollout (the :func:`tasks.physics.mpm_rollout.mpm_rollout` arguments) up to the predicted peak frame +
    ``extra``; returns per frame ``tilt`` (deg), ``slide`` and ``lift`` (mm), ``strain`` (1), ``ke_ie`` (contact
    KE/IE), and ``held`` (pinned particles), ``footprint``, ``peak_frame``, ``predicted`` (peak, 1), ``seconds``
    (wall, the frames only), ``substeps``.  ``snapshots``: a path prefix; side views of the particles after the
    preload, at the predicted peak and at the last frame run are written there as PNG."""
    regions = squeeze_regions(obj_attrs, field, patches, len(times))
    last, target = calibration_window(regions.predicted)
    stop = min(last + extra, len(times) - 1)
    scene = build_scene(obj, obj_attrs, field, patches, times, materials, mpm, sim, forces, boundary, preloaded)
    s = scene.solver
    body = s.mat_field.numpy()[s.material_ids()] == 0
    foot = table_footprint(s)
    x0, m = s.positions().astype(np.float64), s.physical_masses().astype(np.float64)
    if snapshots:
        side_views(x0, body, foot, f"{snapshots}_f0.png", "after the preload")
    out: dict[str, list] = {"tilt": [0.0], "slide": [0.0], "lift": [0.0]}

    def keep_going(f: int, strain: np.ndarray) -> bool:
        x = s.positions().astype(np.float64)
        still = body & (s.mat_field.numpy()[s.material_ids()] == 0)
        out["tilt"].append(body_tilt(x0[still], x[still], m[still]))
        d = (x[foot] - x0[foot]).mean(axis=0) * 1e3 if len(foot) else np.zeros(3)
        out["slide"].append(float(np.hypot(d[0], d[1])))
        out["lift"].append(float(d[2]))
        if snapshots and f == last:
            side_views(x, body, foot, f"{snapshots}_f{f}.png", f"frame {f}: the predicted peak")
        return f < stop

    t0 = time.perf_counter()
    rec = run_frames(scene, obj, field, forces, patches, times, sim, boundary, keep_going)
    seconds = time.perf_counter() - t0
    n = len(out["tilt"])
    if snapshots:
        side_views(s.positions().astype(np.float64), body, foot, f"{snapshots}_f{n - 1}.png", f"frame {n - 1}")
    res = {k: np.asarray(v) for k, v in out.items()}
    res.update(strain=rec.strain[:n].max(axis=1), ke_ie=rec.stats["ke_ie_contact"][:n],
               held=0 if scene.hold is None else len(scene.hold.indices), footprint=len(foot), peak_frame=last,
               predicted=target, seconds=seconds, substeps=int(rec.stats["substeps"][:n].sum()), frames=n - 1)
    return res


def side_views(x: np.ndarray, body: np.ndarray, foot: np.ndarray, path: str, title: str) -> None:
    """Two side views (x-z, y-z) of particles ``x`` (n, 3) m: the body grey, other material blue, the footprint red."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 4.5))
    for ax, (i, name) in zip(axes, ((0, "x"), (1, "y"))):
        ax.scatter(x[body, i] * 1e3, x[body, 2] * 1e3, s=1, c="0.5")
        ax.scatter(x[~body, i] * 1e3, x[~body, 2] * 1e3, s=1, c="tab:blue")
        ax.scatter(x[foot, i] * 1e3, x[foot, 2] * 1e3, s=4, c="tab:red")
        ax.set_xlabel(f"{name} (mm)")
        ax.set_ylabel("z (mm)")
        ax.set_aspect("equal")
    fig.suptitle(title)
    fig.savefig(path, dpi=80)
    plt.close(fig)


def summary(res: dict) -> str:
    """One line: held / footprint particles, peak tilt, slide and lift, peak strain (over the run and up to the
    predicted peak's frame, the force-matched calibration's window) / predicted, KE/IE, time."""
    ke = res["ke_ie"][np.isfinite(res["ke_ie"])]
    return (f"held {res['held']} / footprint {res['footprint']}, frames {res['frames']} (peak {res['peak_frame']}): "
            f"tilt max {res['tilt'].max():.2f} deg (end {res['tilt'][-1]:.2f}), slide max {res['slide'].max():.2f} mm,"
            f" lift max {res['lift'].max():.2f} mm, strain peak {res['strain'].max():.3f} (up to the predicted peak "
            f"{res['strain'][:res['peak_frame'] + 1].max():.3f}) / predicted {res['predicted']:.3f}, KE/IE max {ke.max() if len(ke) else math.nan:.3g}, "
            f"{res['seconds']:.0f} s, {res['substeps']} substeps")
