"""The rubber ball's wall force against a finite-element reference:  ``python -m flows.ball_study``.

    python -m flows.ball_study                         # default grid and 3, 2 mm particles; flats to 6 mm
    python -m flows.ball_study --spacings --travel 4   # the default grid alone, 4 mm
    python -m flows.ball_study --plates grid surface   # grid-node flats and surface flats, each grid
    python -m flows.ball_study --spacings --travel 3 --hold 20 --plates grid surface   # then held 20 s: creep?
    python -m flows.ball_study --spacings 2 1.6 --travel 3 --plates surface            # refined: does it dimple?
    python -m flows.ball_study --spacings 2 --travel 3 --plates surface --extra mpm.dx=0.008   # particles alone
    python -m flows.ball_study --spacings 2 1.6 --travel 3 --plates surface --extra sampling.thin_wall_layers=3
    python -m flows.ball_study --spacings 2 1.6 --travel 3 --plates surface \
        --extra sampling.thin_wall_layers=3 mpm.thin_walls=solid       # the same wall as a 3D solid
    python -m flows.ball_study --spacings 2 1.6 --travel 3 --plates surface \
        --extra mpm.membrane_max_thickness=1   # plane stress up to a cell thick (over 3/4 of a cell: 3D by default)

The default grid's hollow rubber ball (its own particles and materials: the object model and material oracle steps
of :func:`flows.pipeline.run_object_local`, the rollout's scene :func:`tasks.physics.mpm_rollout.build_scene`, no
gravity) squeezed between two frictionless flats (:func:`tasks.verification.contact.body_between_flats`), each
moving ``--travel`` mm towards the other, against the axisymmetric finite-strain FE of the same hollow sphere
between flats (:func:`tasks.verification.sphere_fe.sphere_between_flats` with ``wall``, fixed-corotated: the wall's
radius, thickness, E and nu from the scene; no air inside in either).  ``--spacings`` (mm) refine the particles,
the grid with them (dx = 2 x spacing, substeps 800 / spacing per frame as in ``flows.finger_study``).  ``--plates``:
``grid`` (default) flats of grid-node slip points (their ~1.5-cell halo holds the wall before it touches, as
``mpm.fingers=dirichlet`` does), ``surface`` plane colliders with ``mpm.contact=surface`` (acting where the
particles touch): the difference is the halo's share of the error, the rest the MPM shell's own (README, known
limits).  Prints the force per flat at each whole millimetre of travel, with the pole gap at the press's end (below;
the FE's too), and writes ``<out>/ball_study.md``.  ``--extra``: config overrides added to every MPM run (``mpm.dx``
refines the grid without the particles, a spacing the particles without the grid).  ``--hold`` (s) then keeps the
flats still that long and adds a table of the held force (an elastic wall's stays; the thin wall's crept until its
zero-energy modes were removed, README, known limits) and the pole gap (the wall under a flat's centre sinking away
from it, as a dimpling cap's does).  No Prefect: one process.
"""
from __future__ import annotations

import argparse
import platform
from datetime import datetime
from pathlib import Path

import numpy as np

HOLD_MARKS = (1.0, 2.0, 5.0, 10.0, 20.0, 40.0)  # s: when the held force is reported (those within --hold)
FE_STEP = 0.25e-3  # m: the FE's default depth increment (Newton from the previous depth's state; 0.5 mm steps fail)


def ball_scene(overrides: list[str], root: str, obj: str = "rubber_ball"):
    """The rollout's scene of ``obj`` (full variant, no gravity) on the default grid config plus ``overrides``.  A
    wall sampled in Gauss layers but held as a 3D solid (``mpm.thin_walls=solid``, or thicker than
    ``mpm.membrane_max_thickness`` of a cell) touches the flats at its faces as the plane-stress wall does
    (:func:`tasks.physics.mpm_rollout.build_scene`), not half a particle spacing out."""
    from flows.pipeline import evaluate_config, run_object_local, step_params
    from tasks.core.artifacts import read_artifact
    from tasks.physics.mpm_rollout import build_scene, mpm_rollout_step

    cfg = evaluate_config([f"object={obj}", "variant=full", "mpm.gravity=[0,0,0]", "mpm.energy_guard_tolerance=0",
                           *overrides])
    refs = run_object_local(cfg, cfg.object, cfg.variant, root, until="material_oracle")
    a = {k: read_artifact(v) for k, v in refs.items()}
    params = step_params(mpm_rollout_step, cfg, cfg.object, cfg.variant)
    model = a["object_model"]
    scene = build_scene(model.arrays, {**model.attrs, "name": model.ref.scope}, a["dirichlet_field"].arrays,
                        a["contact_patches"].arrays, a["signal_smoothing"]["time"],
                        a["material_oracle"].attrs["materials"], params["mpm"], params["simulation"],
                        a["force_coefficients"]["force_coefficients"], "dirichlet")
    return scene, cfg


def _row(name: str, force: np.ndarray, note: str) -> str:
    """One markdown table row: the run, its force per flat (N) at each mark, a note."""
    return f"| {name} | " + " | ".join(f"{v:.2f}" for v in force) + f" | {note} |"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spacings", nargs="*", type=float, default=[3.0, 2.0], help="finer particle spacings (mm)")
    ap.add_argument("--travel", type=float, default=6.0, help="each flat's travel (mm)")
    ap.add_argument("--frames", type=int, default=60, help="output frames of the squeeze (1/30 s each)")
    ap.add_argument("--plates", nargs="+", choices=["grid", "surface"], default=["grid"],
                    help="the flats: grid-node slip points and/or surface plane colliders")
    ap.add_argument("--hold", type=float, default=0.0, help="then hold the flats still this long (s)")
    ap.add_argument("--extra", nargs="*", default=[], help="config overrides added to every MPM run "
                    "(e.g. mpm.dx=0.004 to refine the grid alone, object.material.poisson_ratio=0.3)")
    ap.add_argument("--fe-step", type=float, default=1e3 * FE_STEP, help="the FE's depth increment (mm; a 1.5 mm "
                    "wall needs 0.125: Newton starts from the last depth's state)")
    ap.add_argument("--artifacts", default="artifacts", help="artifact root of the object model steps")
    ap.add_argument("--out", default="reports/ball", help="folder of ball_study.md")
    args = ap.parse_args(argv)
    if not args.travel > 0 or any(not v > 0 for v in args.spacings):
        ap.error("--travel and --spacings must be > 0 mm")
    if not args.hold >= 0:
        ap.error("--hold must be >= 0 s")
    if not 0 < args.fe_step <= args.travel:
        ap.error("--fe-step must be > 0 mm and at most --travel")
    from tasks.physics.labels import SHELL
    from tasks.verification.contact import body_between_flats
    from tasks.verification.sphere_fe import sphere_between_flats

    travel = 1e-3 * args.travel
    marks = np.arange(1, int(np.floor(args.travel)) + 1) * 1e-3
    rows, held_rows, wall = [], [], None
    hold_marks = np.array([t for t in HOLD_MARKS if t <= args.hold] + ([args.hold] if args.hold not in HOLD_MARKS
                                                                        and args.hold > 0 else []))
    for spacing in [None, *sorted(args.spacings, reverse=True)]:
        for plate in args.plates:
            over = [] if spacing is None else [f"sampling.particle_spacing={spacing / 1000:g}",
                                               f"mpm.target_substeps_per_frame={round(800 / spacing)}"]
            scene, cfg = ball_scene([*over, f"mpm.contact={plate}", *args.extra], args.artifacts)
            shell = scene.materials[int(scene.slot[SHELL])]
            wall = wall or dict(R=0.5 * float(cfg.object.geometry.size[0]),
                                t=float(cfg.object.geometry.wall_thickness),
                                E=float(shell.youngs_modulus), nu=float(shell.poisson_ratio))
            n_hold = int(round(args.hold / scene.frame_dt))
            r = body_between_flats(scene.solver, plate, travel, args.frames * scene.frame_dt, args.frames, n_hold)
            force = np.interp(marks, r["depth"], r["force"])
            name = f"MPM, dx {1e3 * scene.dx:g} mm" + (" (default)" if spacing is None else "") + f", {plate} flats"
            rows.append((name, force,
                         f"{len(scene.solver.positions())} particles, {r['substeps']} substeps, {r['seconds']:.0f} s; "
                         f"pole gap {1e3 * r['pole_gap'][args.frames - 1]:.2f} mm"))
            print(_row(*rows[-1]), flush=True)
            if n_hold:
                at = np.clip(np.round(hold_marks / scene.frame_dt).astype(int) - 1, 0, n_hold - 1)
                gap = 1e3 * r["pole_gap"][[args.frames - 1, -1]]
                held_rows.append((name, np.array([r["force"][-1], *r["held"][at]]),
                                  f"{100 * (r['held'][-1] / r['force'][-1] - 1):+.1f} % over {args.hold:g} s | "
                                  f"{gap[0]:.2f} -> {gap[1]:.2f}"))
                print(_row(*held_rows[-1]), flush=True)
    step = 1e-3 * args.fe_step
    try:
        fe = sphere_between_flats(np.arange(step, travel + 1e-9, step), wall["R"], wall["E"], wall["nu"],
                                  h_min=wall["t"] / 6, h_max=wall["t"] / 3, model="fixed_corotated", wall=wall["t"],
                                  tol=1e-7)
        rows.append(("FE, finite strain (fixed-corotated)", np.interp(marks, fe["at"], fe["force"]),
                     f"{fe['nodes']} nodes, 3 across the wall; pole gap {1e3 * fe['pole_gap'][-1]:.2f} mm"))
        print(_row(*rows[-1]), flush=True)
    except RuntimeError as exc:  # a thinner wall needs smaller depth steps (1.5 mm: 0.125 mm)
        print(f"no FE reference: {exc}; rerun with a smaller --fe-step (now {args.fe_step:g} mm)", flush=True)
    lines = [f"# Rubber ball between two flats ({datetime.now():%Y-%m-%d %H:%M}, {platform.node()}, Warp CPU)", "",
             f"Hollow sphere R = {1e3 * wall['R']:g} mm, wall {1e3 * wall['t']:g} mm, E = {wall['E']:.3g} Pa, "
             f"nu = {wall['nu']:g}, no air inside; frictionless flats (MPM: grid-node slip points or surface plane "
             "colliders), each moving towards the other.  Force per flat (N) at each flat's travel:", "",
             "| run | " + " | ".join(f"{1e3 * m:g} mm" for m in marks) + " | |",
             "|---|" + "---|" * len(marks) + "---|",
             *[_row(*row) for row in rows]]
    if held_rows:
        lines += ["", f"Held at {args.travel:g} mm: force per flat (N) at the end of the press and after each time "
                  "(s) of the hold (an elastic wall's force stays), and the pole gap (mm): how far the wall under each "
                  "flat's centre has left it, press end -> hold end (the FE keeps the whole flattened disc in contact, "
                  "0; > 0: the cap dimples away from the flat):", "",
                  "| run | press end | " + " | ".join(f"{t:g} s" for t in hold_marks) + " | change | pole gap |",
                  "|---|---|" + "---|" * len(hold_marks) + "---|---|", *[_row(*row) for row in held_rows]]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "ball_study.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {out / 'ball_study.md'}")


if __name__ == "__main__":
    main()
