"""The rubber ball's wall force against a finite-element reference:  ``python -m flows.studies.ball``.

    python -m flows.studies.ball                              # default grid and 3, 2 mm particles; flats to 6 mm
    python -m flows.studies.ball spacings=[] travel=4         # the default grid alone, 4 mm
    python -m flows.studies.ball plates=[grid,surface]        # grid-node flats and surface flats, each grid
    python -m flows.studies.ball spacings=[] travel=3 hold=20 plates=[grid,surface]   # then held 20 s: creep?
    python -m flows.studies.ball spacings=[2,1.6] travel=3 plates=[surface]           # refined: does it dimple?
    python -m flows.studies.ball spacings=[2] travel=3 plates=[surface] mpm.dx=0.008  # particles alone
    python -m flows.studies.ball spacings=[2,1.6] travel=3 plates=[surface] sampling.thin_wall_layers=3
    python -m flows.studies.ball spacings=[2,1.6] travel=3 plates=[surface] \
        sampling.thin_wall_layers=3 mpm.thin_walls=solid       # the same wall as a 3D solid
    python -m flows.studies.ball spacings=[2,1.6] travel=3 plates=[surface] \
        mpm.membrane_max_thickness=1   # plane stress up to a cell thick (over 3/4 of a cell: 3D by default)

The default grid's hollow rubber ball (its own particles and materials: the object model and material oracle steps
of :func:`flows.pipeline.run_object_local`, the rollout's scene :func:`tasks.verification.ball.ball_scene`, no
gravity) squeezed between two frictionless flats (:func:`tasks.verification.contact.body_between_flats`), each
moving ``travel`` mm towards the other, against the axisymmetric finite-strain FE of the same hollow sphere
between flats (:func:`tasks.verification.sphere_fe.sphere_between_flats` with ``wall``, fixed-corotated: the wall's
radius, thickness, E and nu from the scene; no air inside in either).  ``spacings`` (mm) refine the particles,
the grid with them (dx = 2 x spacing, substeps 800 / spacing per frame as in ``flows.studies.fingers``).
``plates``: ``grid`` (default) flats of grid-node slip points (their ~1.5-cell halo holds the wall before it
touches, as ``mpm.fingers=dirichlet`` does), ``surface`` plane colliders with ``mpm.contact=surface`` (acting where
the particles touch): the difference is the halo's share of the error, the rest the MPM shell's own (README, known
limits).  Prints the force per flat at each whole millimetre of travel, with the pole gap at the press's end (below;
the FE's too), and writes ``<out>/ball_study.md``.  The pipeline keys given on the command line (``mpm.*``,
``sampling.*``, ``object.*``, ``paths.artifacts``) are added to every MPM run (``mpm.dx`` refines the grid without
the particles, a spacing the particles without the grid).  ``hold`` (s) then keeps the flats still that long and
adds a table of the held force (an elastic wall's stays; the thin wall's crept until its zero-energy modes were
removed, docs/limits/thin-walls.md) and the pole gap (the wall under a flat's centre sinking away from it, as a dimpling
cap's does).  No Prefect: one process.  Config: ``conf/study/ball.yaml``.
"""
from __future__ import annotations

import platform
from datetime import datetime
from pathlib import Path

import hydra
import numpy as np
from omegaconf import DictConfig

from conf.study.schema import BallStudyConfig, register_study_configs

register_study_configs()


def scene_of(overrides: list[str]):
    """The ball's scene (:func:`tasks.verification.ball.ball_scene`) on the pipeline's config with ``overrides``
    after the ball's own (``BALL_OVERRIDES``), its object steps run (or served from the cache) under
    ``paths.artifacts``; returns the scene and the config."""
    from flows.pipeline import evaluate_config, run_object_local, step_params
    from tasks.physics.mpm_rollout import mpm_rollout_step
    from tasks.verification.ball import BALL_OVERRIDES, UNTIL, ball_scene

    cfg = evaluate_config([*BALL_OVERRIDES, *overrides])
    refs = run_object_local(cfg, cfg.object, cfg.variant, cfg.paths.artifacts, until=UNTIL)
    return ball_scene(refs, step_params(mpm_rollout_step, cfg, cfg.object, cfg.variant)), cfg


@hydra.main(version_base="1.3", config_path="../../conf", config_name="study/ball")
def main(cfg: DictConfig) -> None:
    from flows.studies.overrides import pipeline_overrides

    if not cfg.travel > 0 or any(not v > 0 for v in cfg.spacings):
        raise SystemExit(f"input error: travel and spacings must be > 0 mm, got {cfg.travel:g} and "
                         f"{list(cfg.spacings)}")
    if not cfg.hold >= 0:
        raise SystemExit(f"input error: hold must be >= 0 s, got {cfg.hold:g}")
    if not 0 < cfg.fe_step <= cfg.travel:
        raise SystemExit(f"input error: fe_step must be > 0 mm and at most travel ({cfg.travel:g} mm), got "
                         f"{cfg.fe_step:g}")
    for bad in (p for p in cfg.plates if p not in ("grid", "surface")):
        raise SystemExit(f"input error: plates: unknown flats {bad!r}; grid and/or surface")
    extra = pipeline_overrides(BallStudyConfig)
    from tasks.physics.labels import SHELL
    from tasks.verification.ball import force_row, hold_marks
    from tasks.verification.contact import body_between_flats
    from tasks.verification.convergence import spacing_overrides
    from tasks.verification.sphere_fe import sphere_between_flats

    travel = 1e-3 * cfg.travel
    marks = np.arange(1, int(np.floor(cfg.travel)) + 1) * 1e-3
    rows, held_rows, wall = [], [], None
    marks_held = hold_marks(float(cfg.hold))
    for spacing in [None, *sorted(cfg.spacings, reverse=True)]:
        for plate in cfg.plates:
            scene, run_cfg = scene_of([*spacing_overrides(spacing), f"mpm.contact={plate}", *extra])
            shell = scene.materials[int(scene.slot[SHELL])]
            wall = wall or dict(R=0.5 * float(run_cfg.object.geometry.size[0]),
                                t=float(run_cfg.object.geometry.wall_thickness),
                                E=float(shell.youngs_modulus), nu=float(shell.poisson_ratio))
            n_hold = int(round(cfg.hold / scene.frame_dt))
            r = body_between_flats(scene.solver, plate, travel, cfg.frames * scene.frame_dt, cfg.frames, n_hold)
            force = np.interp(marks, r["depth"], r["force"])
            name = f"MPM, dx {1e3 * scene.dx:g} mm" + (" (default)" if spacing is None else "") + f", {plate} flats"
            rows.append((name, force,
                         f"{len(scene.solver.positions())} particles, {r['substeps']} substeps, {r['seconds']:.0f} s; "
                         f"pole gap {1e3 * r['pole_gap'][cfg.frames - 1]:.2f} mm"))
            print(force_row(*rows[-1]), flush=True)
            if n_hold:
                at = np.clip(np.round(marks_held / scene.frame_dt).astype(int) - 1, 0, n_hold - 1)
                gap = 1e3 * r["pole_gap"][[cfg.frames - 1, -1]]
                held_rows.append((name, np.array([r["force"][-1], *r["held"][at]]),
                                  f"{100 * (r['held'][-1] / r['force'][-1] - 1):+.1f} % over {cfg.hold:g} s | "
                                  f"{gap[0]:.2f} -> {gap[1]:.2f}"))
                print(force_row(*held_rows[-1]), flush=True)
    step = 1e-3 * cfg.fe_step
    try:
        fe = sphere_between_flats(np.arange(step, travel + 1e-9, step), wall["R"], wall["E"], wall["nu"],
                                  h_min=wall["t"] / 6, h_max=wall["t"] / 3, model="fixed_corotated", wall=wall["t"],
                                  tol=1e-7)
        rows.append(("FE, finite strain (fixed-corotated)", np.interp(marks, fe["at"], fe["force"]),
                     f"{fe['nodes']} nodes, 3 across the wall; pole gap {1e3 * fe['pole_gap'][-1]:.2f} mm"))
        print(force_row(*rows[-1]), flush=True)
    except RuntimeError as exc:  # a thinner wall needs smaller depth steps (1.5 mm: 0.125 mm)
        print(f"no FE reference: {exc}; rerun with a smaller fe_step (now {cfg.fe_step:g} mm)", flush=True)
    lines = [f"# Rubber ball between two flats ({datetime.now():%Y-%m-%d %H:%M}, {platform.node()}, Warp CPU)", "",
             f"Hollow sphere R = {1e3 * wall['R']:g} mm, wall {1e3 * wall['t']:g} mm, E = {wall['E']:.3g} Pa, "
             f"nu = {wall['nu']:g}, no air inside; frictionless flats (MPM: grid-node slip points or surface plane "
             "colliders), each moving towards the other.  Force per flat (N) at each flat's travel:", "",
             "| run | " + " | ".join(f"{1e3 * m:g} mm" for m in marks) + " | |",
             "|---|" + "---|" * len(marks) + "---|",
             *[force_row(*row) for row in rows]]
    if held_rows:
        lines += ["", f"Held at {cfg.travel:g} mm: force per flat (N) at the end of the press and after each time "
                  "(s) of the hold (an elastic wall's force stays), and the pole gap (mm): how far the wall under each "
                  "flat's centre has left it, press end -> hold end (the FE keeps the whole flattened disc in contact, "
                  "0; > 0: the cap dimples away from the flat):", "",
                  "| run | press end | " + " | ".join(f"{t:g} s" for t in marks_held) + " | change | pole gap |",
                  "|---|---|" + "---|" * len(marks_held) + "---|---|", *[force_row(*row) for row in held_rows]]
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "ball_study.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {out / 'ball_study.md'}")


if __name__ == "__main__":
    main()
