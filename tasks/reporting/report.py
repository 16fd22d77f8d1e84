"""Run reports: the per-task table, per-object control plots, and where every artifact lives.

Writes ``<report_dir>/report.md``, ``index.html`` (self-contained: images embedded, opens offline),
``tasks.csv`` and one PNG per object.  Pure functions of artifacts; the flow calls :func:`write_run_report`.
"""
from __future__ import annotations

import base64
import html
import json
import subprocess
import tempfile
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence

import matplotlib.pyplot as plt  # headless: matplotlib picks its Agg backend when there is no display
import numpy as np

from conf.hand import FINGERS
from conf.mpm_schema import MPMConfig
from tasks.core.artifacts import ArtifactError, ArtifactRef, read_artifact
from tasks.core.scope import split_seed_scope
from tasks.core.tables import markdown_table
from tasks.physics.free_flight import rollout_flights
from tasks.reporting.media_cache import MEDIA_DIR, MediaCache
from tasks.reporting.render_knobs import report_section as render_knob_section
from tasks.reporting.video_tables import paper_metric_reasons, table1, table3, video_metric_rows
from tasks.reporting.watch import STYLE, SYNC_SCRIPT, object_html, object_media, overview_html, overview_sheet


def code_revision() -> str:
    """The git revision of the code that produced the run (``unknown`` outside a checkout)."""
    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                             cwd=Path(__file__).parent, timeout=5)
        dirty = subprocess.run(["git", "status", "--porcelain"], capture_output=True, text=True,
                               cwd=Path(__file__).parent, timeout=5)
        return rev.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "") if rev.returncode == 0 else "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def _save(fig, axes, path: Path, dpi: int = 110) -> Path:
    """Grid lines on every axis, tight layout, PNG at ``path``; the figure is closed."""
    for ax in np.ravel(axes):
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def control_figure(obj: str, refs: Mapping[str, Optional[ArtifactRef]], path: Path) -> Optional[Path]:
    """Flexion, force coefficients (eq. 1) and contact patch area (eq. 2) per finger over time."""
    try:
        frames = read_artifact(refs["signal_smoothing"])
        forces = read_artifact(refs["force_coefficients"])
        patches = read_artifact(refs["contact_patches"])
    except (KeyError, TypeError, ArtifactError, AttributeError):
        return None
    t = frames["time"]
    fig, axes = plt.subplots(3, 1, figsize=(7.5, 6.6), sharex=True)
    for k, finger in enumerate(FINGERS):
        axes[0].plot(t, frames["flexion_raw"][:, k], color=f"C{k}", alpha=0.3, lw=0.8)
        axes[0].plot(t, frames["flexion"][:, k], color=f"C{k}", label=finger)
        axes[1].plot(t, forces["force_coefficients"][:, k], color=f"C{k}")
        axes[2].plot(t, patches["patch_areas"][:, k] * 1e4, color=f"C{k}")
    axes[0].set_ylabel("flexion (1)\nfaint: resampled raw")
    axes[1].set_ylabel("force coeff. c (1)")
    axes[2].set_ylabel("patch area (cm$^2$)")
    axes[2].set_xlabel("time (s)")
    axes[0].legend(ncol=5, fontsize=8, loc="upper right")
    axes[0].set_title(f"{obj}: squeezing control mapping")
    return _save(fig, axes, path)


def rollout_figure(obj: str, refs: Mapping[str, Optional[ArtifactRef]], path: Path) -> Optional[Path]:
    """Deformation over time (squeeze strain per finger: simulated vs prescribed by eq. 3, volume change),
    reaction and resistive feedback force per finger, and the solver's substeps per frame."""
    try:
        r = read_artifact(refs["mpm_rollout"], names=[
            "time", "squeeze_strain", "predicted_squeeze_strain", "reaction_force", "applied_force",
            "feedback_force", "substeps", "particle_J"])
    except (KeyError, TypeError, ArtifactError, AttributeError):
        return None
    t = r["time"]
    fig, axes = plt.subplots(4, 1, figsize=(7.5, 8.4), sharex=True)
    for k, finger in enumerate(FINGERS):
        axes[0].plot(t, r["squeeze_strain"][:, k], color=f"C{k}", label=finger)
        axes[0].plot(t, r["predicted_squeeze_strain"][:, k], color=f"C{k}", ls=":", lw=1)
        force = r["reaction_force"] if r.attrs["boundary"] == "dirichlet" else r["applied_force"]
        axes[1].plot(t, np.linalg.norm(force[:, k], axis=-1), color=f"C{k}")
        axes[1].plot(t, r["feedback_force"][:, k], color=f"C{k}", ls="--", lw=1)
    event = r.attrs.get("threshold_event", {})
    if event.get("threshold") is not None:
        axes[0].axhline(event["threshold"], color="k", lw=0.8, ls="--", label="threshold")
    if event.get("crossed"):
        for ax in axes:
            ax.axvline(event["time"], color="r", lw=0.8)
    axes[0].set_ylabel("squeeze strain (1)\ndotted: prescribed")
    axes[0].legend(ncol=6, fontsize=7, loc="upper right")
    axes[1].set_ylabel("contact force (N)\ndashed: feedback")
    vol = r["particle_J"].mean(axis=1) - 1.0
    axes[2].plot(t, 100 * vol, color="k")
    axes[2].set_ylabel("mean volume\nchange (%)")
    axes[3].plot(t, r["substeps"], color="k")
    axes[3].set_ylabel("substeps / frame")
    axes[3].set_xlabel("time (s)")
    axes[0].set_title(f"{obj}: MPM rollout ({r.attrs['boundary']}, mass scale x{r.attrs['mass_scale']:.3g})")
    return _save(fig, axes, path)


def snapshot_figure(obj: str, refs: Mapping[str, Optional[ArtifactRef]], path: Path) -> Optional[Path]:
    """Particles at rest, at peak squeeze and at the end, seen from the side (x-z) and from above (x-y),
    coloured by von Mises stress; interior particles in blue, released ones in orange."""
    try:
        r = read_artifact(refs["mpm_rollout"], names=[
            "particle_positions", "particle_von_mises", "particle_material", "squeeze_strain", "released", "time"])
    except (KeyError, TypeError, ArtifactError, AttributeError):
        return None
    eps = r["squeeze_strain"].max(axis=1)
    frames = [("rest", 0), ("peak squeeze", int(np.argmax(eps))), ("end", len(eps) - 1)]
    x_all = r["particle_positions"]
    lo, hi = x_all.reshape(-1, 3).min(axis=0), x_all.reshape(-1, 3).max(axis=0)
    mat = r["particle_material"]
    released = r["released"] if "released" in r else np.zeros(len(mat), bool)
    vmax = max(float(np.percentile(r["particle_von_mises"], 99)), 1e-9)
    fig, axes = plt.subplots(2, 3, figsize=(9, 6))
    for col, (label, f) in enumerate(frames):
        x = x_all[f]
        shell = mat != 1
        for row, (a, b, names) in enumerate(((0, 2, "x-z"), (0, 1, "x-y"))):
            ax = axes[row, col]
            ax.scatter(x[shell, a], x[shell, b], c=r["particle_von_mises"][f][shell], s=2, cmap="viridis",
                       vmin=0, vmax=vmax)
            inner = ~shell & ~released
            ax.scatter(x[inner, a], x[inner, b], s=1, color="tab:blue", alpha=0.3)
            ax.scatter(x[released, a], x[released, b], s=2, color="tab:orange")
            ax.set_xlim(lo[a], hi[a])
            ax.set_ylim(lo[b], hi[b])
            ax.set_aspect("equal")
            ax.set_xticks([])
            ax.set_yticks([])
            if row == 0:
                ax.set_title(f"{label}, t={r['time'][f]:.2f} s", fontsize=9)
            if col == 0:
                ax.set_ylabel(names)
    fig.suptitle(f"{obj}: particles (colour: von Mises stress up to {vmax:.3g} Pa)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


FLIGHT_NAMES = ("released_flight_time", "released_flight_positions", "released_flight_held", "released_flight_mass",
                "released_flight_physical_mass")
FLIGHTS_DRAWN = 6  # the longest flights the flight figure draws


def flight_figure(obj: str, refs: Mapping[str, Optional[ArtifactRef]], path: Path) -> Optional[Path]:
    """The released material's flight (sec. 3.2: released particles under gravity, :mod:`tasks.physics.free_flight`):
    the centre-of-mass height of each of the longest free blobs' flights (a fixed set of particles touching
    nothing through the grid) per sample of the rollout's sub-frame flight recorder, each against its own free-fall
    parabola z0 + v0 t + a_exp t^2 / 2 (a_exp = g for released material; z0, v0 fitted); below, the recorded loose
    material's height range (median, 10-90 %; what stays held throughout, e.g. cola in its can, is not recorded),
    the share of its particles held (in a blob, linked by shared grid nodes, one of whose particles shares a grid node
    with the body, a boundary point, a wall or the table) and the share in the measured free blobs.  The title states the acceleration measured.  None without a
    release."""
    try:
        r = read_artifact(refs["mpm_rollout"], names=list(FLIGHT_NAMES))
    except (KeyError, TypeError, ArtifactError, AttributeError):
        return None
    if "released_flight_positions" not in r:
        return None
    fall = r.attrs.get("released_free_fall") or {}
    # heights above the table where the rollout recorded its height (earlier rollouts: world z)
    table = fall.get("floor_height")
    base, above = (table, "above the table ") if table is not None else (0.0, "")
    t, z, held = r["released_flight_time"], r["released_flight_positions"][..., 2].astype(np.float64) - base, \
        r["released_flight_held"]
    flights = rollout_flights({k: r[k] for k in FLIGHT_NAMES}, fall) if "grid_origin" in fall else []
    fig, axes = plt.subplots(2, 1, figsize=(5.5, 6.0), sharex=True, height_ratios=(3, 2))
    for i, fl in enumerate(flights[:FLIGHTS_DRAWN]):
        tf = fl.times - fl.times[0]
        z0, v0 = np.linalg.lstsq(np.stack([np.ones_like(tf), tf], 1), fl.height - 0.5 * fl.expected * tf ** 2,
                                 rcond=None)[0]
        axes[0].plot(fl.times, 1e3 * (fl.height - base), ".", ms=3, color=f"C{i}",
                     label=f"{len(fl.members)} particles: a = {fl.acceleration:.2f} m/s^2")
        axes[0].plot(fl.times, 1e3 * (z0 + v0 * tf + 0.5 * fl.expected * tf ** 2 - base), "-", lw=1, color=f"C{i}")
    if not flights:
        axes[0].text(0.5, 0.5, "no free blob: the released material stays coupled through\nthe grid to the body, "
                     "the table or a wall", transform=axes[0].transAxes, ha="center", va="center", fontsize=8)
        axes[0].set_yticks([])
    else:
        axes[0].plot([], [], "-", color="k", lw=1, label="free fall, each flight's own z0, v0")
        axes[0].legend(fontsize=7)
        axes[0].set_ylabel(f"centre-of-mass height {above}of\neach free blob (mm)")
    if not z.shape[1]:  # every released particle stayed held throughout: the record keeps none (free_flight)
        axes[1].text(0.5, 0.5, "every released particle stayed held throughout the recording", fontsize=8,
                     transform=axes[1].transAxes, ha="center", va="center")
    else:
        lo, mid, hi = np.percentile(z, [10, 50, 90], axis=1)
        axes[1].fill_between(t, 1e3 * lo, 1e3 * hi, color="tab:orange", alpha=0.3, lw=0,
                             label="recorded loose material 10-90 %")
        axes[1].plot(t, 1e3 * mid, color="tab:orange", lw=1, label="median")
        axes[1].set_ylabel(f"height {above}(mm)")
        axes[1].set_xlabel("time (s)")
        share = axes[1].twinx()
        share.plot(t, held.mean(axis=1), color="k", lw=1, ls="--", label="held (right)")
        flying = np.zeros(len(t))
        for fl in flights:
            flying[fl.start:fl.stop] += len(fl.members) / held.shape[1]
        share.plot(t, flying, color="C2", lw=1, ls=":", label="in free blobs (right)")
        share.set_ylim(0, 1.05)
        share.set_ylabel("share of the recorded particles")
        axes[1].legend(fontsize=7, loc="lower left")
        share.legend(fontsize=7, loc="lower right")
        axes[1].set_xlim(t[0] - 0.005, t[-1] + 0.005)
    axes[0].set_title(f"{obj}\n" + flight_caption(fall), fontsize=8)
    return _save(fig, axes, path)


def flight_caption(fall: Optional[Mapping[str, Any]]) -> str:
    """One line on the released material's measured free fall (the rollout's ``released_free_fall`` attrs)."""
    if not fall or fall.get("acceleration") is None:
        return "released material: no free blob flew for 4 recorder samples (a = none)"
    a, err = fall["acceleration"], fall["error"]
    return (f"released material: a = {a:.2f} m/s^2 ({100 * err:+.1f} % of the expected {fall['expected']:.2f}), "
            f"median of {fall['flights']} free blobs'\nflights ({fall['particles']} particles), longest "
            f"{1e3 * fall['longest_flight']:.0f} ms")


FIGURE_INPUTS = {"control": ("signal_smoothing", "force_coefficients", "contact_patches"), "metric_bars": (),
                 "rollout": ("mpm_rollout",), "snapshot": ("mpm_rollout",), "flight": ("mpm_rollout",)}  # the artifacts each figure draws


def _variant_refs(refs: Mapping[str, Mapping[str, Any]]):
    """(object, variant, that pair's refs = shared steps + the variant's own) for every simulated pair."""
    for obj, obj_refs in refs.items():
        shared = {k: v for k, v in obj_refs.items() if k != "variants"}
        for variant, vrefs in obj_refs.get("variants", {}).items():
            yield obj, variant, {**shared, **vrefs}


def rollout_summary(refs: Mapping[str, Mapping[str, Any]]) -> Optional[str]:
    """One markdown row per object and variant: particles, substeps, time scaling, threshold event, notes."""
    rows = []
    for obj, variant, pair in _variant_refs(refs):
        ref = pair.get("mpm_rollout")
        if ref is None:
            continue
        try:
            r = read_artifact(ref, names=["squeeze_strain", "dirichlet_tracking_error", "ke_ie_ratio", "feedback_force"])
        except ArtifactError:
            continue
        a = r.attrs
        ev = a["threshold_event"]
        event = (f"crossed at {ev['time']:.2f} s (strain {ev['strain']:.3f} >= {ev['threshold']}), "
                 f"{ev['released_particles']} released" if ev.get("crossed")
                 else ("never crossed" if ev.get("threshold") is not None else "no threshold"))
        attached = a.get("skin_attachment") or {}
        if attached.get("ruptured_detached") is not None:  # the skin stays on the object (tasks.physics.attachment)
            event += (f"; torn skin > 3 cells off the object {attached['ruptured_detached']:.0%} "
                      f"(intact shell {attached['shell_detached']:.0%})")
        if attached.get("stuffing_detached") is not None:  # torn-out stuffing held by its contact (Material.cohesion)
            event += f", stuffing {attached['stuffing_detached']:.0%}"
        eps = r["squeeze_strain"].max(axis=1)
        qs = a.get("quasi_static", {})
        tracking = (f"{1e3 * r['dirichlet_tracking_error'].max():.2f}" if a["boundary"] == "dirichlet" else "-")
        rows.append(f"| {obj} | {variant} | {a['n_particles']} | {a['substeps_total']} | x{a['mass_scale']:.3g} | "
                    f"{quasi_static_cell(qs)} | {eps.max():.3f} / {eps[-1]:.3f} | {tracking} | "
                    f"{r['feedback_force'].max():.1f} | {event} | {ref.compute_seconds:.1f} |")
    if not rows:
        return None
    head = ("| object | variant | particles | substeps | mass scale | quasi-static check: max KE/IE / limit | "
            "squeeze strain peak / end | max tracking error (mm) | peak feedback (N) | threshold | sim compute (s) |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|")
    return head + "\n" + "\n".join(rows)


def quasi_static_cell(qs: Mapping[str, Any]) -> str:
    """The rollout's quasi-static check (its ``quasi_static`` attrs) as the solver applied it: the largest value of
    its measure (sum KE / sum (IE + plastic work) of the mass-scaled material over a contact) over the contacts it
    judged, its limit ``mpm.quasi_static_ke_ie_max``, whether it warned, and how many contacts and frames it
    checked."""
    n = int(qs.get("contacts_checked", 0))
    if not n:
        return "not checked (no mass scaling or no loaded frame)"
    over = int(qs.get("contacts_over_limit", 0))
    verdict = f"WARNED in {over} of {n} contact(s)" if over else f"ok in {n} contact(s)"
    peak = qs["max_ke_ie_in_contact"]  # None: kinetic energy without internal energy
    return f"{'inf' if peak is None else format(peak, '.3g')} / {qs['limit']:g}: {verdict} " \
           f"({qs.get('frames_checked', 0)} frames checked)"


def effect_notes(refs: Mapping[str, Mapping[str, Any]]) -> list[str]:
    """Per object, variant and backend: which effect was generated (and how it is labelled), or why it was
    skipped (no released material, generation=none)."""
    lines = []
    for obj, variant, pair in _variant_refs(refs):
        for backend, brefs in pair.get("backends", {}).items():
            ref = brefs.get("effect")
            if ref is None:
                continue
            try:
                attrs = read_artifact(ref, names=[]).attrs
            except ArtifactError:
                continue
            what = (f"effect skipped: {attrs['skipped']}" if attrs.get("skipped")
                    else f"effect: {attrs.get('label')}")
            lines.append(f"- {obj} [{variant}, {backend}]: {what}")
    return lines


def left_out(refs: Mapping[str, Mapping[str, Any]]) -> list[str]:
    """Per object and variant, what the run left out of the scene and why (the rollout's own notes)."""
    lines = []
    for obj, variant, pair in _variant_refs(refs):
        ref = pair.get("mpm_rollout")
        if ref is None:
            lines.append(f"- {obj} [{variant}]: not simulated (an upstream step failed; see the task table)")
            continue
        try:
            notes = read_artifact(ref, names=[]).attrs.get("notes", [])
        except ArtifactError:
            continue
        lines.append(f"- {obj} [{variant}]: " + ("; ".join(notes) if notes else "nothing left out"))
    return lines


def wall_findings(refs: Mapping[str, Mapping[str, Any]]) -> list[str]:
    """Per object whose wall the grid cannot resolve, or whose wall over half a cell thick is sampled in two Gauss
    layers: the thin-wall finding (:mod:`tasks.physics.wall_resolution`)."""
    from tasks.physics.material_oracle import materials_from_dict
    from tasks.physics.wall_resolution import thin_wall_finding

    lines = []
    for obj, obj_refs in refs.items():
        rollout = next((v.get("mpm_rollout") for v in obj_refs.get("variants", {}).values() if v.get("mpm_rollout")), None)
        if rollout is None or any(obj_refs.get(s) is None for s in ("object_model", "mpm_particles", "material_oracle")):
            continue
        try:  # the wall's sampling (thin_wall, its layers) is the particles'
            shape = {**read_artifact(obj_refs["object_model"], names=[]).attrs,
                     **read_artifact(obj_refs["mpm_particles"], names=[]).attrs}
            shell = materials_from_dict(read_artifact(obj_refs["material_oracle"], names=[]).attrs["materials"]).shell
            run = read_artifact(rollout, names=[]).attrs
            dx = float(run["dx"])
        except (ArtifactError, KeyError):
            continue
        limit = float(run.get("membrane_max_thickness", MPMConfig.membrane_max_thickness))  # older runs: the default
        finding = thin_wall_finding(shape, dx, shell.poisson_ratio, shell.youngs_modulus, name=obj,
                                    membrane_max_thickness=limit)
        if finding.flagged or finding.advice:
            lines.append(f"- {obj}: {finding.message}")
    return lines


def metric_bars_figure(obj: str, df, labels: Mapping[str, str], path: Path) -> Optional[Path]:
    """The four Table 2 scores of one object, one bar per variant."""
    from tasks.reporting.report_tables import TABLE2

    name, seed = split_seed_scope(obj)
    sub = df[(df["object"] == name) & (df["seed"] == seed)] if len(df) else df
    if sub is None or len(sub) == 0:
        return None
    fig, ax = plt.subplots(figsize=(6.5, 2.8))
    width = 0.8 / len(sub)
    for i, (_, row) in enumerate(sub.iterrows()):
        vals = [row.get(key, np.nan) for key, _, _ in TABLE2]
        ax.bar(np.arange(len(TABLE2)) + i * width, vals, width, label=labels.get(row["variant"], row["variant"]))
    ax.set_xticks(np.arange(len(TABLE2)) + 0.4 - width / 2, [name for _, name, _ in TABLE2])
    ax.set_ylim(0, 1)
    ax.set_ylabel("score (1)")
    ax.legend(fontsize=7, loc="lower right")
    ax.set_title(f"{obj}: squeezing-controlled deformation metrics", fontsize=10)
    return _save(fig, ax, path)


def _figure(cache: MediaCache, kind: str, draw, title: str, inputs: Mapping[str, Any], path: Path,
            params: Optional[Mapping[str, Any]] = None) -> Optional[Path]:
    """The figure ``kind`` at ``path``: drawn once per content (``draw(title, inputs, path)``), then reused from
    ``cache``."""
    return cache.get(path, cache.key(kind, {"title": title, **(params or {})}, {k: inputs.get(k) for k in
                     FIGURE_INPUTS[kind]}), lambda p: draw(title, inputs, p))


def scene_figures(cache: MediaCache, obj: str, variant: str, pair: Mapping[str, Any], out_dir: Path) -> list[Path]:
    """The rollout and particle-snapshot figures of one object and variant (``pair``: its refs), in ``out_dir``, and
    beside the snapshots the released material's flight (with a release)."""
    return [p for p in [
        _figure(cache, "rollout", rollout_figure, f"{obj} [{variant}]", pair, out_dir / f"{obj}_{variant}_rollout.png"),
        _figure(cache, "snapshot", snapshot_figure, f"{obj} [{variant}]", pair,
                out_dir / f"{obj}_{variant}_snapshots.png"),
        _figure(cache, "flight", flight_figure, f"{obj} [{variant}]", pair, out_dir / f"{obj}_{variant}_flight.png")]
        if p]


# The steps whose artifacts the media of one scene show (videos, contact sheet, signal and scene figures)
SCENE_MEDIA_INPUTS = ("signal_smoothing", "force_coefficients", "contact_patches", "mpm_rollout", "gbuffer",
                      "conditions", "effect", "appearance_refinement", "display_video")


def cache_scene_media(obj: str, obj_refs: Mapping[str, Any], variant: str, root: str, first: bool) -> int:
    """Make the media the report shows of one scene (object ``obj``, ``variant``) in the media cache
    ``<root>/.media`` as soon as the scene's artifacts exist, so that the report build only links them: the
    videos, loss curve and figures of the scene and, for the object's ``first`` variant, the object's contact
    sheet, signal plots and control figure.  ``obj_refs`` is the object's reference tree as
    :func:`write_run_report` reads it, with ``variant`` as its only variant and (at least) the
    :data:`SCENE_MEDIA_INPUTS`.  Returns how many media were made (the others were in the cache already).  Same
    keys, hence the same bytes, as the report build's."""
    def rooted(tree):
        return ({k: rooted(v) for k, v in tree.items()} if isinstance(tree, Mapping)
                else tree.at(root) if isinstance(tree, ArtifactRef) else tree)

    obj_refs = rooted(obj_refs)
    cache = MediaCache(Path(root) / MEDIA_DIR)
    with tempfile.TemporaryDirectory(prefix="scene-media-") as scratch:
        object_media(obj, obj_refs, Path(scratch), cache, scenes_only=not first)
        pair = {**{k: v for k, v in obj_refs.items() if k != "variants"}, **obj_refs["variants"][variant]}
        scene_figures(cache, obj, variant, pair, Path(scratch))
        if first:
            _figure(cache, "control", control_figure, obj, obj_refs, Path(scratch) / f"{obj}_control.png")
    return cache.made


def _first_scene(obj_refs: Mapping[str, Any]) -> dict[str, Any]:
    """The references the overview contact sheet reads of one object: its first variant's G-buffer, rollout and
    first backend's display video."""
    variant = next(iter(obj_refs.get("variants", {}).values()), {})
    backend = next(iter(variant.get("backends", {}).values()), {})
    return {"gbuffer": variant.get("gbuffer"), "mpm_rollout": variant.get("mpm_rollout"),
            "display_video": backend.get("display_video")}


def _embed(png: Path) -> str:
    return "data:image/png;base64," + base64.b64encode(png.read_bytes()).decode()


def viewer_lines(report_dir: Path, refs: Mapping[str, Mapping[str, Any]]) -> list[str]:
    """The report's pointer to the interactive 4D viewer, with links to the offline recordings of this run's
    scenes that ``python -m flows.view record=true`` wrote beside the report (``../viewer/``)."""
    from tasks.reporting.viewer_scene import recording_name

    folder = report_dir.parent / "viewer"
    found = [(scope, variant, folder / recording_name(scope, variant)) for scope, obj_refs in refs.items()
             for variant in obj_refs.get("variants", {})]
    links = [f"[{scope} {variant}](../viewer/{path.name})" for scope, variant, path in found if path.exists()]
    return ["Look at a squeeze from anywhere, scrub its time and compare the variants in the browser: "
            "`python -m flows.view object=<name>` with this run's overrides (docs/tutorials/viewer.md); "
            "`record=true` writes a recording that plays without a server"
            + (": " + ", ".join(links) if links else " (none written yet for this run's scenes)") + ".", ""]


def write_run_report(report_dir: Path, *, cfg: Mapping[str, Any], table, refs: Mapping[str, Mapping[str, Any]],
                     wall_seconds: float, variants: Optional[Mapping[str, str]] = None,
                     sections: Optional[list[tuple[str, str]]] = None,
                     missing_backends: Optional[Mapping[str, str]] = None, profile: str = "",
                     media_cache: Optional[Path] = None, shared_media: Sequence[Path] = ()) -> Path:
    """Write the report folder for one flow run and return the path of ``report.md``.

    ``refs[object]`` holds the shared steps' references and ``refs[object]["variants"][variant]`` the
    per-variant ones (``...["backends"][backend]`` the per-backend ones); ``variants`` maps variant names to their
    labels (Table 2's "Method").  ``sections`` are extra (title, markdown) blocks; ``missing_backends`` names the
    effect backends the run could not use and why (Table 1's n/a rows); ``profile`` is the compute-per-stage
    table of the run.  ``media_cache`` (``<artifacts>/.media``) keeps every video and figure by content
    (:mod:`tasks.reporting.media_cache`): a report of unchanged artifacts encodes and draws nothing.  Media are
    also looked up, never written, in ``shared_media`` (a read-only artifacts cache's ``.media``).
    """
    from tasks.reporting.report_tables import (
        TABLE2,
        TRAJECTORY,
        force_match_note,
        html_table,
        metric_rows,
        paper_layout,
        seed_note,
        stored_definitions,
        with_paper_rows,
        write_metric_files,
    )

    report_dir = Path(report_dir)
    report_dir.mkdir(parents=True, exist_ok=True)
    labels = dict(variants or {})
    df = table.frame()
    df.to_csv(report_dir / "tasks.csv", index=False)
    (report_dir / "config.json").write_text(json.dumps(cfg, indent=2, default=str))
    revision = code_revision()
    metrics = metric_rows(refs)
    video = video_metric_rows(refs)
    write_metric_files(metrics.merge(video, on=["object", "seed", "variant"], how="left") if len(video) and len(metrics)
                       else metrics, report_dir)
    objects = list(dict.fromkeys(split_seed_scope(key)[0] for key in refs))
    for v in (metrics["variant"].unique() if len(metrics) else []):
        labels.setdefault(v, v)
    tables = [(title, *paper_layout(metrics, keys, objects, labels)) for title, keys in
              (("Squeezing-controlled deformation (paper Table 2 layout; bold: best variant per column)", TABLE2),
               ("Trajectory metrics: sensed hand motion vs reconstructed deformation (paper Supplementary Part 6)",
                TRAJECTORY))]
    tables[0] = with_paper_rows(*tables[0], objects)  # the paper's Table 2 beside ours (never bold)
    physical_cols = [c for c in metrics.columns
                     if c not in {"object", "seed", "variant"} | {k for k, _, _ in TABLE2 + TRAJECTORY}]
    physical = metrics[["object", "seed", "variant", *physical_cols]] if len(metrics) else metrics
    definitions = {**stored_definitions(refs, "deformation_metrics"), **stored_definitions(refs, "video_metrics"),
                   **stored_definitions(refs, "paper_metrics")}
    video_tables = [
        ("Video metrics, paper Table 1 layout (mean over the objects where every method has a value; bold: best, "
         "never in a column true by construction; the paper's rows below ours)",
         *table1(video, labels, missing_backends or {})),
        ("Video metrics per object, paper Table 3 layout", *table3(video, objects, labels)),
    ]
    note, n_seeds = seed_note(metrics), len(set(metrics["seed"])) if len(metrics) else 1
    captions = {title: note for title, *_ in tables} if note else {}
    strength = force_match_note(refs, labels)  # the ablation's input strength, under Table 2
    if strength and tables[0][2]:
        captions[tables[0][0]] = " ".join(x for x in (captions.get(tables[0][0]), strength) if x)
    if n_seeds > 1:
        captions.update({title: f"Mean over the {n_seeds} sampling seeds (per-seed rows in metrics.csv)."
                         for title, *_ in video_tables})
    cache = MediaCache(media_cache, shared_media)
    media = [m for m in (object_media(obj, refs[obj], report_dir, cache) for obj in refs) if m is not None]
    sheet_inputs = {f"{obj}/{k}": ref for obj in refs for k, ref in _first_scene(refs[obj]).items()}
    sheet = cache.get(report_dir / "contact_sheet.png", cache.key("overview_sheet", {}, sheet_inputs),
                      lambda p: overview_sheet(refs, p))
    figures: dict[str, list[Path]] = {}
    for obj in refs:
        name, seed = split_seed_scope(obj)
        bars = metrics[(metrics["object"] == name) & (metrics["seed"] == seed)].to_dict("records") if len(metrics) \
            else []
        figures[obj] = [p for p in [
            _figure(cache, "control", control_figure, obj, refs[obj], report_dir / f"{obj}_control.png"),
            _figure(cache, "metric_bars", lambda t, _, p: metric_bars_figure(t, metrics, labels, p), obj, {},
                    report_dir / f"{obj}_metrics.png", {"rows": bars, "labels": labels})] if p]
    for obj, variant, pair in _variant_refs(refs):
        figures[obj] += scene_figures(cache, obj, variant, pair, report_dir)

    summary = rollout_summary(refs)
    knobs = render_knob_section(cfg)  # the latest render/effect knob study: time and error per setting
    sections = ([("Squeeze simulation (MPM)", summary)] if summary else []) + list(sections or []) + (
        [knobs] if knobs else [])
    md = [f"# VirSqueezer run `{report_dir.name}`", "",
          f"- wall time: {wall_seconds:.1f} s; tasks: {table.summary()}; peak memory of the flow process "
          f"{peak_rss_mb():.0f} MB (Dask workers not included)",
          f"- code revision: `{revision}`; config: `config.json`; metric rows: `metrics.csv`, `metrics.parquet`",
          "- accuracy preset: " + ("; ".join(f"{k} {v}" for k, v in cfg.get("accuracy", {}).items())
                                   or "none stated (no preset selected)"),
          "- variants: " + ", ".join(f"`{k}` = {v}" for k, v in labels.items()), ""]
    warned = [f"- {r.object} {r.step}{f' [{r.variant}]' if r.variant else ''}: {r.warning}"
              for r in table.rows if r.warning]
    md += ["## Warnings", "", *warned, ""] if warned else []
    md += ["![rest, peak squeeze, after release of every object](contact_sheet.png)", ""] if sheet else []
    md += ["## Watch the squeezes", "", "Open `index.html` for the videos: per object and variant the simulated "
           "render, the conditions of eq. 6, the final composite and the refined 4D Gaussians, with the control "
           "signals in sync.  Files: " + ", ".join(f"`{s.stages_video.name}`" for m in media for s in m.scenes
                                                  if s.stages_video), ""]
    md += viewer_lines(report_dir, refs)
    for title, header, rows, best in tables + video_tables:
        md += [f"## {title}", "", markdown_table(header, rows, best) if rows else "(no metrics: see the task table)", ""]
        md += [captions[title], ""] if title in captions and rows else []
    paper_reasons = paper_metric_reasons(refs)
    md += ["Paper metrics not computed here: " + "; ".join(f"{k}: {v}" for k, v in paper_reasons.items()), ""]
    if profile:
        md += ["## Profile: compute per stage and object", "", profile, ""]
    if len(physical):
        md += ["## Physical figures per object and variant", "",
               markdown_table(list(physical.columns), [[_fmt(x) for x in r] for r in physical.itertuples(index=False)]), ""]
    walls = wall_findings(refs)
    omitted = [*left_out(refs), *effect_notes(refs)]
    md += ["## Left out of each scene, and why", "", *omitted, ""]
    if walls:
        md += ["## Walls thinner than the grid resolves (python -m flows.studies.stability)", "", *walls, ""]
    md += ["## Compute per step (tasks that ran in this run)", "", step_shares(df), ""]
    md += ["## Per-task table", "", "```", table.to_text(), "```", ""]
    for title, body in sections:
        md += [f"## {title}", "", body, ""]
    if definitions:
        md += ["## Metric definitions", ""] + [f"- **{k}**: {v}" for k, v in definitions.items()] + [""]
    md += ["## Objects", ""]
    by_obj = {m.obj: m for m in media}
    for obj in refs:
        md.append(f"### {obj}")
        if obj in by_obj and by_obj[obj].contact_sheet:
            md.append(f"![{obj} contact sheet]({by_obj[obj].contact_sheet.name})")
        md += [f"![{png.stem}]({png.name})" for png in figures.get(obj, [])]
        md += ["", "| step | variant | artifact |", "|---|---|---|"]
        md += [f"| {r.step} | {r.variant or '-'} | `{r.artifact or '(not produced)'}` |"
               for r in table.rows if r.object == obj]
        md.append("")
    (report_dir / "report.md").write_text("\n".join(md))

    body = [f"<h1>VirSqueezer run {html.escape(report_dir.name)}</h1>",
            f"<p>wall time {wall_seconds:.1f} s; tasks: {html.escape(table.summary())}; code revision "
            f"<code>{html.escape(revision)}</code>; metric rows in metrics.csv / metrics.parquet</p>",
            "<p>accuracy preset: " + html.escape("; ".join(f"{k} {v}" for k, v in cfg.get("accuracy", {}).items())
                                                 or "none stated") + "</p>"]
    body += ["<h2>Warnings</h2>", "<ul>" + "".join(f"<li>{html.escape(w[2:])}</li>" for w in warned) + "</ul>"
             ] if warned else []
    if sheet:
        body += ["<h2>The squeezes at a glance: rest, peak squeeze, after release (view 1, the hand drawn)</h2>",
                 f'<p><img alt="contact sheet" style="max-width:100%" src="{_embed(sheet)}"></p>']
    if media:
        body += ["<h2>Overview: the watched video of every squeeze (view 0 and the close-up of the contact)</h2>",
                 overview_html(media, labels)]
    for title, header, rows, best in tables + video_tables:
        body += [f"<h2>{html.escape(title)}</h2>", html_table(header, rows, best) if rows else "<p>(no metrics)</p>"]
        body += [f"<p>{html.escape(captions[title])}</p>"] if title in captions and rows else []
    body.append("<p>Paper metrics not computed here: " + html.escape(
        "; ".join(f"{k}: {v}" for k, v in paper_reasons.items())) + "</p>")
    if profile:
        body += ["<h2>Profile: compute per stage and object</h2>", f"<pre>{html.escape(profile)}</pre>"]
    if len(physical):
        body += ["<h2>Physical figures per object and variant</h2>",
                 html_table(list(physical.columns), [[_fmt(x) for x in r] for r in physical.itertuples(index=False)])]
    body += ["<h2>Left out of each scene, and why</h2>", "<ul>" + "".join(
        f"<li>{html.escape(line[2:])}</li>" for line in omitted) + "</ul>"]
    if walls:
        body += ["<h2>Walls thinner than the grid resolves</h2>",
                 "<ul>" + "".join(f"<li>{html.escape(line[2:])}</li>" for line in walls) + "</ul>"]
    body += ["<h2>Compute per step (tasks that ran in this run)</h2>", f"<pre>{html.escape(step_shares(df))}</pre>"]
    body += ["<h2>Per-task table</h2>", df.drop(columns=["artifact"]).to_html(index=False, float_format="%.2f")]
    for title, text in sections:
        body += [f"<h2>{html.escape(title)}</h2>", f"<pre>{html.escape(text)}</pre>"]
    if definitions:
        body += ["<h2>Metric definitions</h2>", "<dl>" + "".join(
            f"<dt><b>{html.escape(k)}</b></dt><dd>{html.escape(v)}</dd>" for k, v in definitions.items()) + "</dl>"]
    body.append("<h2>Objects</h2>")
    for obj in refs:
        body.append(f"<h3>{html.escape(obj)}</h3>")
        if obj in by_obj:
            body.append(object_html(by_obj[obj], labels))
        for png in figures.get(obj, []):
            body.append(f'<img alt="{html.escape(png.stem)}" src="{_embed(png)}" style="max-width:800px">')
        body.append("<ul>" + "".join(
            f"<li>{html.escape(r.step)}{' [' + html.escape(r.variant) + ']' if r.variant else ''}: "
            f"<code>{html.escape(r.artifact or '(not produced)')}</code></li>" for r in table.rows if r.object == obj)
            + "</ul>")
    body += ["<h2>Config</h2>", f"<pre>{html.escape(json.dumps(cfg, indent=2, default=str))}</pre>"]
    page = ("<!doctype html><html><head><meta charset='utf-8'><title>VirSqueezer report</title>"
            "<style>body{font-family:sans-serif;max-width:1100px;margin:auto}table{border-collapse:collapse}"
            "td,th{border:1px solid #ccc;padding:2px 6px;font-size:13px}" + STYLE + "</style></head><body>"
            + "\n".join(body) + SYNC_SCRIPT + "</body></html>")
    (report_dir / "index.html").write_text(page)
    return report_dir / "report.md"


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far (MB; Linux reports ru_maxrss in kB)."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def step_shares(df) -> str:
    """Markdown table: compute seconds and share of the run's compute per step (tasks that ran, not cached)."""
    ran = df[df["status"] == "ran"]
    if ran.empty:
        return "(every task was cached: no compute in this run)"
    per = ran.groupby("step")["wall_seconds"].agg(["sum", "count"]).sort_values("sum", ascending=False)
    total = float(per["sum"].sum())
    rows = [[step, str(int(r["count"])), f"{r['sum']:.1f}", f"{100 * r['sum'] / max(total, 1e-12):.1f} %"]
            for step, r in per.iterrows()]
    return markdown_table(["step", "tasks", "compute (s)", "share"], rows)


def _fmt(x: Any) -> str:
    """Cell text: 4 significant digits for numbers, '-' for NaN."""
    if isinstance(x, (float, np.floating)):
        return "-" if not np.isfinite(x) else f"{x:.4g}"
    return str(x)
