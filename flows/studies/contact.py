"""Contact convergence study:  ``python -m flows.studies.contact`` (grid vs surface contact, force error against dx).

    python -m flows.studies.contact                 # Hertz R/dx = 8, 12, 16; indentation; uniaxial L/dx = 8, 12, 16
    python -m flows.studies.contact hertz_cells=[8] indent_cells=[2] uniaxial_cells=[8] nu=[0.3]   # quick
    python -m flows.studies.contact hertz_cells=[] indent_cells=[] uniaxial_cells=[] finger_cells=[1,1.5,2]  # fingers

Wires :mod:`tasks.verification.contact` (Hertz: elastic sphere between two flats, also against a finite-sphere
FE (:mod:`tasks.verification.sphere_fe`), and a rigid sphere indenting a block; uniaxial compression between
frictionless plates; each with ``mpm.contact = grid`` and ``surface``, the plates also as particle pins): prints
one line per case (force error, contact radius error, particles, wall seconds) and writes
``<out>/contact_study.md``.  No Prefect: short diagnostics run in this process, one after the other.
Config: ``conf/study/contact.yaml`` (keys: :class:`conf.study.schema.ContactStudyConfig`).
"""
from __future__ import annotations

import platform
from datetime import datetime
from pathlib import Path

import hydra
from omegaconf import DictConfig

from conf.study.schema import register_study_configs

register_study_configs()


@hydra.main(version_base="1.3", config_path="../../conf", config_name="study/contact")
def main(cfg: DictConfig) -> None:
    for key, allowed in (("modes", ("grid", "surface")), ("uniaxial_modes", ("grid", "surface", "pins"))):
        for bad in (m for m in cfg[key] if m not in allowed):
            raise SystemExit(f"input error: {key}: unknown contact {bad!r}; one of {list(allowed)}")
    from tasks.verification.contact import (
        HERTZ_DEPTHS,
        HERTZ_E,
        HERTZ_R,
        fingertip_case,
        hertz_case,
        hertz_force,
        indentation_case,
        summary_line,
        uniaxial_case,
    )
    from tasks.verification.sphere_fe import sphere_between_flats

    lines = [f"# Contact study ({datetime.now():%Y-%m-%d %H:%M}, {platform.node()}, Warp CPU)", "",
             "Force error = simulated / closed form - 1.  Hertz: sphere R = 35 mm, E = 2 MPa between two "
             "frictionless flats, each approaching its centre by d; radius = flattened patch against a = sqrt(R d).  "
             "Indentation: rigid sphere collider R = 35 mm into a nu = 0.45 block (8 a wide, 5 a deep).  Uniaxial: "
             "cube L = 40 mm, E = 0.1 MPa, frictionless plates (grid nodes, plane colliders or pinned particle "
             "layers), lateral faces free, force at 1 % plate travel "
             "against E A eps.  Seconds: wall time of the run on this (shared) machine.", "",
             "## Hertz", ""]
    pct = lambda v: " / ".join(f"{100 * e:+.1f}%" for e in v)  # noqa: E731
    if cfg.hertz_cells:
        lines += ["The finite sphere itself (axisymmetric FE, `tasks.verification.sphere_fe`) against Hertz at "
                  "1/2/3/4 mm: small strain (linear) and finite strain (fixed-corotated, the solver's model); `vs FE` "
                  "is the simulation against the finite-strain FE.", ""]
        fe = {}
        for nu in cfg.hertz_nu:
            for model in ("linear", "fixed_corotated"):
                r = sphere_between_flats(HERTZ_DEPTHS, HERTZ_R, HERTZ_E, nu, growth=0.1, model=model)
                err = pct(r["force"] / hertz_force(r["at"], HERTZ_R, HERTZ_E, nu) - 1.0)
                print(f"hertz    finite-sphere FE ({model}, nu {nu:g}, {r['nodes']} nodes) against Hertz: {err}",
                      flush=True)
                lines.append(f"- nu = {nu:g}, {model}: {err}")
                if model == "fixed_corotated":  # the reference of `vs FE`
                    fe[nu] = r["force"]
        lines += ["", "| contact | nu | R/dx | dx (mm) | force err 1/2/3/4 mm | vs FE | radius err 1/2/3/4 mm "
                  "| particles | seconds |", "|---|---|---|---|---|---|---|---|---|"]
    for nu in cfg.hertz_nu if cfg.hertz_cells else ():
        for n in cfg.hertz_cells:
            for mode in cfg.modes:
                r = hertz_case(mode, n, nu=nu)
                vs_fe = r["force_at"] / fe[nu] - 1.0
                print(summary_line(r, "hertz", f"nu {nu:g}, against the finite-strain FE {pct(vs_fe)}"), flush=True)
                lines.append(f"| {mode} | {nu:g} | {n} | {1e3 * r['dx']:.3g} | {pct(r['force_error'])} "
                             f"| {pct(vs_fe)} | {pct(r['radius_error'])} | {r['particles']} | {r['seconds']:.0f} |")
    surface_sections = [
        ("indent", "Rigid sphere indenting a block (surface contact)", "a/dx at 4 mm", "2, 3, 4", "2/3/4",
         indentation_case, cfg.indent_cells),
        ("finger", "Collider finger driven by the eq. 3 field into a block (Hertz, R = fingertip pad 10 mm)",
         "a/dx at 2 mm", "1, 1.5, 2", "1/1.5/2", fingertip_case, cfg.finger_cells)]
    for label, title, column, depths, depth_cols, case, cells in surface_sections:
        lines += ["", f"## {title}", "", f"| {column} | dx (mm) | force err {depth_cols} mm | particles | seconds |",
                  "|---|---|---|---|---|"]
        for c in cells:
            r = case(c)
            print(f"{label:<8} surface a/dx={c:g} dx={1e3 * r['dx']:.3g} mm force err at {depths} mm: "
                  f"{pct(r['force_error'])}; {r['particles']} particles, {r['seconds']:.1f} s", flush=True)
            lines.append(f"| {c:g} | {1e3 * r['dx']:.3g} | {pct(r['force_error'])} | {r['particles']} "
                         f"| {r['seconds']:.0f} |")
    lines += ["", "## Uniaxial compression", "", "| contact | L/dx | nu | force err | particles | seconds |",
              "|---|---|---|---|---|---|"]
    for n in cfg.uniaxial_cells:
        for nu in cfg.nu:
            for mode in cfg.uniaxial_modes:
                r = uniaxial_case(mode, nu, n)
                print(summary_line(r, "uniaxial"), flush=True)
                lines.append(f"| {mode} | {n} | {nu:g} | {100 * r['error']:+.1f}% | {r['particles']} "
                             f"| {r['seconds']:.0f} |")
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "contact_study.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {out / 'contact_study.md'}")


if __name__ == "__main__":
    main()
