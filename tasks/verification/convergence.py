"""Error against run time (``python -m flows.studies.convergence``): how far a cheaper solver setting's rollout is
from a reference rollout at the finest affordable setting, and what it costs.

Pure functions (numpy/pandas/matplotlib; no Prefect): the error measures between two rollouts of the same object
and session, the Pareto front of (wall seconds, error), the observed convergence order, building one setting's
config from the base config, and the report.  :mod:`flows.studies.convergence` wires them to the cached pipeline
steps.

Error measures (all dimensionless):

* ``position_error``: RMS over all frames and all tracked surface Gaussians of ``|x - x_ref|``, divided by the
  object's bounding-box diagonal.  The Gaussians are tracers embedded in the nearest particles, so the same points
  are compared across settings as long as the surface sampling (``sampling.surface_points``, ``sampling.seed``)
  is unchanged; the volume particle spacing does not move them.
* ``final_position_error``: the same at the last frame only (the residual dent or rebound after release).
* ``reaction_force_error``: per-finger reaction magnitude ``|R_k(t)|`` (N), L2 over frames and fingers of the
  difference to the reference, divided by the reference's L2.
* ``peak_strain_error``: per-finger peak squeeze strain ``max_t eps_k(t)`` (the deformation the rupture threshold
  is tested against), L2 over fingers of the difference, divided by the reference's L2.

Observed order: for settings that refine one discretisation parameter ``h`` (grid spacing dx, or the substep
dt) with everything else as in the reference, ``e ~ C h^p``; ``p`` is the least-squares slope of log e against
log h over the settings (the reference itself, error 0, is excluded), plus the pairwise slopes of successive
refinements.
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from conf.study.convergence_schema import ERROR_COLUMNS

NOT_SWEPT = (
    ("The render and effect knobs (render.width/height, render.frame_stride, refinement.iterations) have their "
     "own study, python -m flows.studies.render_convergence (every run report shows its latest tables); this one "
     "compares the physics (the deformation chain) only.  generation.steps is not measured: its error needs the "
     "diffusion weights, which are not on this machine."),
    ("`sampling.surface_points` (the number of 3D Gaussians, also the contact surface) is not swept: it changes "
    "the tracked points themselves, so there is nothing to compare positions against."),
    ("`mpm.cells_across` does not act in the rollout: the grid spacing is always `mpm.dx` when set, otherwise "
    "`sampling.particle_spacing` x cbrt(`mpm.particles_per_cell`); an explicit `mpm.dx` is the same knob as "
    "`particles_per_cell` at a fixed spacing (the `grid` family)."),
)
ROLLOUT_ARRAYS = ("time", "gaussian_positions", "particle_positions", "reaction_force", "applied_force",
                  "squeeze_strain", "substeps")


class ConvergenceError(ValueError):
    """Two rollouts that cannot be compared, or a sweep that cannot be built (one line, names the fix)."""


# ----------------------------------------------------------------------------------------------- error measures
def bbox_diagonal(bbox_min: Sequence[float], bbox_max: Sequence[float]) -> float:
    """Length (m) of the diagonal of an axis-aligned bounding box."""
    return float(np.linalg.norm(np.asarray(bbox_max, np.float64) - np.asarray(bbox_min, np.float64)))


def _same_shape(a: np.ndarray, b: np.ndarray, what: str) -> None:
    if a.shape != b.shape:
        raise ConvergenceError(f"{what}: shape {a.shape} differs from the reference's {b.shape}; compare rollouts "
                               "of the same object, session, frame rate and surface sampling")


def position_error(positions: np.ndarray, reference: np.ndarray, size: float) -> float:
    """RMS over frames and points of |x - x_ref| (m), divided by ``size`` (m): (frame, point, xyz) arrays."""
    x = np.asarray(positions, np.float64)
    r = np.asarray(reference, np.float64)
    _same_shape(x, r, "gaussian_positions")
    if not size > 0:
        raise ConvergenceError(f"normalising size must be > 0 m, got {size}")
    return float(np.sqrt(np.mean(np.sum((x - r) ** 2, axis=-1))) / size)


def distances_from(positions: Mapping[Any, np.ndarray], references: Mapping[str, Any]) -> dict[Any, dict[str, float]]:
    """Every run's :func:`position_error` from each named reference run, normalised by the bounding-box diagonal of
    the first run's first frame.  ``positions``: run key -> surface trajectories (frame, point, xyz) m (one set of
    points for all); ``references``: name -> key of ``positions``.  Returns run key -> {name: error (1)}."""
    if not positions:
        raise ConvergenceError("no runs to compare: every case failed or none was asked for")
    x0 = np.asarray(next(iter(positions.values())), np.float64)[0]
    diag = bbox_diagonal(x0.min(axis=0), x0.max(axis=0))
    return {key: {name: position_error(x, positions[ref], diag) for name, ref in references.items()}
            for key, x in positions.items()}


def _magnitudes(force: np.ndarray) -> np.ndarray:
    f = np.asarray(force, np.float64)
    return np.linalg.norm(f, axis=-1) if f.ndim == 3 else f


def reaction_force_error(reaction: np.ndarray, reference: np.ndarray) -> float:
    """Relative L2 error of the per-finger reaction magnitudes over frames and fingers.

    ``reaction``/``reference``: (frame, finger, xyz) vectors (N) or (frame, finger) magnitudes.  A reference
    without any force gives 0 when the run has none either, else inf.
    """
    a, b = _magnitudes(reaction), _magnitudes(reference)
    _same_shape(a, b, "reaction_force")
    return _relative_l2(a, b)


def _relative_l2(a: np.ndarray, b: np.ndarray) -> float:
    """|a - b| / |b| (L2 over all entries); 0 when both are zero, inf when only the reference is."""
    norm = float(np.linalg.norm(b))
    diff = float(np.linalg.norm(a - b))
    if norm == 0.0:
        return 0.0 if diff == 0.0 else math.inf
    return diff / norm


def peak_strain_error(strain: np.ndarray, reference: np.ndarray) -> float:
    """Relative L2 error over fingers of the per-finger peak squeeze strain max_t eps_k(t): (frame, finger)."""
    a = np.asarray(strain, np.float64)
    b = np.asarray(reference, np.float64)
    _same_shape(a, b, "squeeze_strain")
    return _relative_l2(a.max(axis=0), b.max(axis=0))


def tracer_drift(tracers: np.ndarray, particles: np.ndarray) -> float:
    """How far (m) the tracked surface Gaussians left the material: max over tracers of the growth, from the first
    to the last frame, of the distance to the nearest simulated particle.  (frame, point, xyz), (frame, particle,
    xyz).  A tracer that follows the surface keeps its distance (~0); one that detaches from the body grows it."""
    from scipy.spatial import cKDTree

    d0, _ = cKDTree(np.asarray(particles[0], np.float64)).query(np.asarray(tracers[0], np.float64))
    d1, _ = cKDTree(np.asarray(particles[-1], np.float64)).query(np.asarray(tracers[-1], np.float64))
    return float(np.max(d1 - d0)) if len(d0) else 0.0


def rollout_errors(run: Mapping[str, np.ndarray], ref: Mapping[str, np.ndarray], size: float,
                   contact: str = "reaction_force") -> dict[str, float]:
    """Every error measure of ``run`` against ``ref`` (mappings of rollout arrays); ``size`` (m) normalises the
    positions; ``contact`` is the force array compared (``applied_force`` for the force-driven variant)."""
    gx, gr = run["gaussian_positions"], ref["gaussian_positions"]
    return {
        "position_error": position_error(gx, gr, size),
        "final_position_error": position_error(gx[-1:], gr[-1:], size),
        "reaction_force_error": reaction_force_error(run[contact], ref[contact]),
        "peak_strain_error": peak_strain_error(run["squeeze_strain"], ref["squeeze_strain"]),
    }


# ----------------------------------------------------------------------------------------------- Pareto front, order
def pareto_front(cost: Sequence[float], error: Sequence[float]) -> np.ndarray:
    """Boolean mask of the points no other point dominates (cost <= and error <=, one of them strictly).

    Points with a non-finite cost or error are never on the front.
    """
    c = np.asarray(cost, np.float64)
    e = np.asarray(error, np.float64)
    ok = np.isfinite(c) & np.isfinite(e)
    front = ok.copy()
    for i in np.flatnonzero(ok):
        dominated = ok & (c <= c[i]) & (e <= e[i]) & ((c < c[i]) | (e < e[i]))
        front[i] = not dominated.any()
    return front


@dataclass(frozen=True)
class OrderFit:
    """Observed convergence order: e ~ C h^p fitted in log-log space over ``n`` settings."""

    p: float
    C: float
    n: int
    pairwise: tuple[float, ...] = field(default_factory=tuple)  # slopes of successive refinements (coarse first)


def observed_order(h: Sequence[float], error: Sequence[float]) -> OrderFit | None:
    """Least-squares slope of log(error) against log(h), and the slopes between successive refinements.

    Points with h <= 0, error <= 0 or non-finite values (e.g. the reference itself, error 0) are left out.
    Returns None with fewer than two usable points or a single distinct h.
    """
    h = np.asarray(h, np.float64)
    e = np.asarray(error, np.float64)
    ok = np.isfinite(h) & np.isfinite(e) & (h > 0) & (e > 0)
    h, e = h[ok], e[ok]
    if len(h) < 2 or np.unique(h).size < 2:
        return None
    order = np.argsort(-h)  # coarse to fine
    lh, le = np.log(h[order]), np.log(e[order])
    p, logc = np.polyfit(lh, le, 1)
    pair = tuple(float((le[i] - le[i + 1]) / (lh[i] - lh[i + 1])) for i in range(len(lh) - 1) if lh[i] != lh[i + 1])
    return OrderFit(p=float(p), C=float(math.exp(logc)), n=len(h), pairwise=pair)


# ----------------------------------------------------------------------------------------------- settings
def load_preset(preset_dir: str | Path, name: str) -> dict[str, Any]:
    """The values a ``conf/preset/<name>.yaml`` (``# @package _global_``) sets, as a nested dict."""
    from omegaconf import OmegaConf

    path = Path(preset_dir) / f"{name}.yaml"
    if not path.is_file():
        known = sorted(p.stem for p in Path(preset_dir).glob("*.yaml"))
        raise ConvergenceError(f"preset {name!r} does not exist ({path}); known presets: {known}")
    return OmegaConf.to_container(OmegaConf.load(path), resolve=True) or {}


def setting_config(base: Any, overrides: Sequence[str], preset: Mapping[str, Any] | None = None):
    """``base`` (a composed, structured DictConfig) with a preset's values and then ``overrides``
    (``key=value`` strings) merged in.  An unknown key or a wrong type is an error naming it."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    try:
        parts = [base]
        if preset:
            parts.append(OmegaConf.create(dict(preset)))
        parts.append(OmegaConf.from_dotlist(list(overrides)))
        return OmegaConf.merge(*parts)
    except OmegaConfBaseException as exc:
        raise ConvergenceError(f"setting overrides {list(overrides)}: {str(exc).splitlines()[0]}") from None


def spacing_overrides(spacing_mm: float | None) -> list[str]:
    """The overrides of one particle spacing (mm), the grid refined with it (dx = 2 x spacing) at the convergence
    study's mass scale s ~ (dt / dx)^2 (``conf/study/convergence.yaml``: target substeps per frame x dx = 1600 mm);
    None: the default grid (4 mm, 100 substeps: a 4x larger mass scale)."""
    if spacing_mm is None:
        return []
    return [f"sampling.particle_spacing={spacing_mm / 1000:g}",
            f"mpm.target_substeps_per_frame={round(800 / spacing_mm)}"]


PRESET_SECTIONS = ("sampling", "mpm", "simulation")  # what a preset may set; a setting equal there sits at it


def matching_presets(setting: Any, presets: Mapping[str, Any]) -> list[str]:
    """Names of the presets whose resolved ``sampling``/``mpm``/``simulation`` sections equal ``setting``'s
    (both composed configs, e.g. from :func:`setting_config`)."""
    from omegaconf import OmegaConf

    def sections(c: Any) -> dict:
        return {k: OmegaConf.to_container(c[k], resolve=True) for k in PRESET_SECTIONS if k in c}

    mine = sections(setting)
    return [name for name, cfg in presets.items() if sections(cfg) == mine]


# ----------------------------------------------------------------------------------------------- measuring
METRIC_NAMES = ("bdc_t", "bdc_s", "sdc", "miou")  # deformation metrics (tasks.evaluation.deformation_metrics) compared


@dataclass
class RolloutRecord:
    """What the sweep needs from one setting's artifacts (loaded once)."""

    arrays: dict[str, np.ndarray]
    attrs: dict[str, Any]
    surface_points: np.ndarray
    bbox_min: list[float]
    bbox_max: list[float]
    particle_spacing: float
    rollout_seconds: float
    pipeline_seconds: float
    metrics: dict[str, float | None] = field(default_factory=dict)


def load_record(refs: Mapping[str, Any]) -> RolloutRecord:
    """Load one setting's rollout, object surface and recorded compute seconds from its artifact references
    (``object_model``, ``mpm_rollout``, optionally ``deformation_metrics``; every step's ref counts in the
    pipeline seconds).  The seconds are those recorded when each step ran (also for cache hits)."""
    from tasks.core.artifacts import read_artifact, read_group_attrs

    roll = read_artifact(refs["mpm_rollout"], names=ROLLOUT_ARRAYS)
    obj = read_artifact(refs["object_model"], names=("surface_points",))
    seconds = {step: float(read_group_attrs(ref.path).get("compute_seconds", 0.0))
               for step, ref in refs.items() if ref is not None}
    metrics: dict[str, float | None] = {}
    if refs.get("deformation_metrics") is not None:
        m = read_artifact(refs["deformation_metrics"], names=()).attrs.get("metrics", {})
        metrics = {k: m.get(k) for k in METRIC_NAMES}
    return RolloutRecord(arrays=roll.arrays, attrs=roll.attrs, surface_points=obj["surface_points"],
                         bbox_min=list(obj.attrs["bbox_min"]), bbox_max=list(obj.attrs["bbox_max"]),
                         particle_spacing=float(obj.attrs["particle_spacing"]),
                         rollout_seconds=seconds["mpm_rollout"], pipeline_seconds=float(sum(seconds.values())),
                         metrics=metrics)


def setting_row(name: str, family: str, cfg: Any, run: RolloutRecord, ref: RolloutRecord) -> dict[str, Any]:
    """One table row: the setting's knobs, its cost and its errors against the reference record."""
    a = run.attrs
    qs = a.get("quasi_static", {})  # the rollout's quasi-static check
    frame_dt = float(np.diff(run.arrays["time"][:2])[0]) if len(run.arrays["time"]) > 1 else float("nan")
    frames = max(len(run.arrays["time"]) - 1, 1)
    substeps = int(a.get("substeps_total", int(np.sum(run.arrays["substeps"]))))
    mpm = cfg.mpm
    row: dict[str, Any] = {
        "setting": name, "family": family, "status": "ok", "note": "",
        "particle_spacing_m": run.particle_spacing, "particles_per_cell": int(mpm.particles_per_cell),
        "dx_m": float(a["dx"]), "courant": float(mpm.courant), "mass_scaling": str(mpm.mass_scaling),
        "target_substeps_per_frame": int(mpm.target_substeps_per_frame), "stiffness_scaling": float(mpm.stiffness_scaling),
        "mass_scale": float(a.get("mass_scale", float("nan"))), "n_particles": int(a["n_particles"]),
        "substeps_total": substeps, "dt_mean_s": frame_dt * frames / max(substeps, 1),
        "ke_ie_max": float(qs["max_ke_ie_in_contact"]) if qs.get("frames_checked") else math.nan,  # NaN: unchecked
        "rollout_s": run.rollout_seconds, "pipeline_s": run.pipeline_seconds,
        "tracer_drift_m": tracer_drift(run.arrays["gaussian_positions"], run.arrays["particle_positions"]),
    }
    if run.surface_points.shape != ref.surface_points.shape or not np.allclose(run.surface_points,
                                                                                 ref.surface_points, atol=1e-7):
        row.update({k: float("nan") for k in ERROR_COLUMNS})
        row["note"] = "surface sampling differs from the reference's: the tracked Gaussians are not comparable"
    else:
        contact = "applied_force" if a.get("boundary") == "force" else "reaction_force"
        row.update(rollout_errors(run.arrays, ref.arrays, bbox_diagonal(ref.bbox_min, ref.bbox_max), contact))
    if row["tracer_drift_m"] > 0.5 * row["dx_m"]:
        row["note"] += (f"surface Gaussians left the material (up to {row['tracer_drift_m'] * 1e3:.1f} mm further from "
                       "the nearest particle at the end than at rest): the position errors include that drift")
    for k in METRIC_NAMES:
        mine, theirs = run.metrics.get(k), ref.metrics.get(k)
        row[f"d_{k}"] = abs(mine - theirs) if mine is not None and theirs is not None else float("nan")
    return row


# ----------------------------------------------------------------------------------------------- table
TABLE_COLUMNS = (
    "setting", "family", "preset", "status", "reference", "particle_spacing_m", "particles_per_cell", "dx_m",
    "courant", "mass_scaling", "target_substeps_per_frame", "stiffness_scaling", "mass_scale", "n_particles",
    "substeps_total", "dt_mean_s", "ke_ie_max", "tracer_drift_m", "rollout_s", "pipeline_s", *ERROR_COLUMNS,
    *(f"d_{k}" for k in METRIC_NAMES), "pareto", "note")


def convergence_table(rows: Sequence[Mapping[str, Any]], reference: str, pareto_on: str = "position_error",
                      cost: str = "pipeline_s") -> pd.DataFrame:
    """The error-vs-time table: one row per setting in the order given, errors against ``reference``, and
    ``pareto`` marking the settings on the Pareto front of (``cost``, ``pareto_on``)."""
    df = pd.DataFrame([dict(r) for r in rows])
    for col in TABLE_COLUMNS:
        if col not in df.columns:
            df[col] = np.nan if col not in ("note", "preset", "status", "family", "mass_scaling") else ""
    df["reference"] = df["setting"] == reference
    ok = df["status"] == "ok"
    front = pareto_front(np.where(ok, df[cost].astype(float), np.nan), np.where(ok, df[pareto_on].astype(float),
                                                                                   np.nan))
    df["pareto"] = front
    return df[list(TABLE_COLUMNS)]


def family_orders(df: pd.DataFrame, families: Mapping[str, str], error: str = "position_error",
                  records: Mapping[str, RolloutRecord] | None = None) -> dict[str, Any]:
    """Observed order per family whose refinement parameter is ``dx`` (dx_m) or ``dt`` (dt_mean_s).

    ``fit``: the family's errors against the sweep's reference (the reference row left out).  With ``records``
    also ``self_fit``: errors against the family's own finest member (smallest h), which removes the error the
    family shares with it (e.g. the spatial error of a time-step family run on a coarser grid than the
    reference); ``self_reference`` names that member.
    """
    out: dict[str, Any] = {}
    for fam, param in families.items():
        if param not in ("dx", "dt"):
            continue
        col = "dx_m" if param == "dx" else "dt_mean_s"
        members = df[(df["family"] == fam) & (df["status"] == "ok")]
        sub = members[~members["reference"] & (members[error].astype(float) > 0)]
        entry: dict[str, Any] = {"parameter": param, "settings": list(sub["setting"]),
                                 "fit": observed_order(sub[col].astype(float), sub[error].astype(float)),
                                 "self_fit": None, "self_reference": None}
        if records is not None and len(members) >= 3:
            finest = members.sort_values(col, kind="stable").iloc[0]
            base = records[finest["setting"]]
            size = bbox_diagonal(base.bbox_min, base.bbox_max)
            others = members[(members["setting"] != finest["setting"]) & (members[col] > finest[col])]
            errs = []
            for name in others["setting"]:
                run = records[name]
                contact = "applied_force" if run.attrs.get("boundary") == "force" else "reaction_force"
                errs.append(rollout_errors(run.arrays, base.arrays, size, contact)[error])
            entry["self_fit"] = observed_order(others[col].astype(float), errs)
            entry["self_reference"] = str(finest["setting"])
            entry["self_settings"] = list(others["setting"])
        out[fam] = entry
    return out


# ----------------------------------------------------------------------------------------------- report
def pareto_figure(df: pd.DataFrame, path: Path, cost: str = "pipeline_s",
                  errors: Sequence[str] = ("position_error", "reaction_force_error")) -> Path:
    """Error against wall time (log-log) per family, Pareto front as a line, presets annotated."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = df[(df["status"] == "ok") & ~df["reference"]]
    fams = list(dict.fromkeys(ok["family"]))
    fig, axes = plt.subplots(1, len(errors), figsize=(6.0 * len(errors), 4.6), squeeze=False)
    for ax, err in zip(axes[0], errors):
        for i, fam in enumerate(fams):
            sub = ok[ok["family"] == fam]
            ax.scatter(sub[cost], sub[err], color=f"C{i % 10}", label=fam, zorder=3)
        for (c, e), g in ok.groupby([cost, err], sort=False):  # identical runs (cache hits) share one label
            ax.annotate(" = ".join(g["setting"]), (c, e), fontsize=7, xytext=(3, 3), textcoords="offset points")
        valid = ok[np.isfinite(ok[err].astype(float)) & (ok[err].astype(float) > 0)]
        if len(valid):
            mask = pareto_front(valid[cost].astype(float), valid[err].astype(float))
            front = valid[mask].sort_values(cost)
            ax.step(front[cost], front[err], where="post", color="k", lw=1.2, label="Pareto front", zorder=2)
        for _, r in ok[ok["preset"].astype(str) != ""].iterrows():
            ax.scatter([r[cost]], [r[err]], s=160, facecolors="none", edgecolors="k", zorder=4)
            ax.annotate(f"preset: {r['preset']}", (r[cost], r[err]), fontsize=8, fontweight="bold",
                        xytext=(4, -12), textcoords="offset points")
        ax.set_xscale("log")
        if (ok[err].astype(float) > 0).any():
            ax.set_yscale("log")
        ax.set_xlabel(f"wall time per object ({cost}, s)")
        ax.set_ylabel(f"{err} (1, against the reference)")
        ax.grid(alpha=0.3, which="both")
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _fmt(x: Any, digits: int = 3) -> str:
    if isinstance(x, (bool, np.bool_)):
        return "yes" if x else ""
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    if isinstance(x, (float, np.floating)):
        if not np.isfinite(x):
            return "" if np.isnan(x) else str(x)
        if x == 0:
            return "0"
        return f"{x:.{digits}g}"
    return "" if x is None else str(x)


def markdown_table(df: pd.DataFrame, columns: Sequence[str]) -> str:
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for _, r in df.iterrows():
        lines.append("| " + " | ".join(_fmt(r[c]) for c in columns) + " |")
    return "\n".join(lines)


def timing_spread(df: pd.DataFrame) -> str:
    """A sentence on the timing noise: settings with the same particles, grid and substeps do the same work, so
    the spread of their rollout seconds is what the machine's load added (empty when no such pair ran)."""
    ok = df[df["status"] == "ok"].drop_duplicates(subset=["rollout_s", "n_particles", "substeps_total", "dx_m"])
    worst = None
    for _, g in ok.groupby(["n_particles", "substeps_total", "dx_m"]):
        if len(g) > 1:
            lo, hi = g["rollout_s"].min(), g["rollout_s"].max()
            if worst is None or hi / lo > worst[1] / worst[0]:
                worst = (lo, hi, list(g["setting"]))
    if worst is None:
        return ""
    return (f"Timing noise: {', '.join(worst[2])} do the same work (particles, grid, substeps) and took "
            f"{worst[0]:.3g}-{worst[1]:.3g} s ({worst[1] / worst[0]:.2g} x); wall-time differences below that "
            "factor are the machine's load, not the setting.")


def preset_summary(df: pd.DataFrame, presets: Sequence[str] = ()) -> str:
    """Which setting each preset sits at, with its measured time and errors (from the table, not estimated)."""
    lines = []
    for name in presets or sorted({p.strip() for v in df["preset"].astype(str) for p in v.split(",") if p.strip()}):
        rows = df[df["preset"].astype(str).str.split(", ").apply(lambda ps, n=name: n in ps)]
        if rows.empty:
            lines.append(f"- **{name}**: no setting of this sweep has its values")
            continue
        r = rows.iloc[0]
        if r["status"] != "ok":
            lines.append(f"- **{name}** = setting `{r['setting']}`: did not finish ({r['note']})")
            continue
        errs = ", ".join(f"{c} {_fmt(r[c])}" for c in ERROR_COLUMNS)
        lines.append(f"- **{name}** = setting `{r['setting']}` (dx {_fmt(r['dx_m'])} m, "
                     f"{_fmt(r['n_particles'])} particles, {_fmt(r['substeps_total'])} substeps): "
                     f"{_fmt(r['pipeline_s'])} s per object (rollout {_fmt(r['rollout_s'])} s); {errs}")
    return "\n".join(lines) if lines else "No preset in this sweep."


def _order_text(fit: OrderFit | None, settings: Sequence[str]) -> str:
    if fit is None:
        return "fewer than two usable settings (" + (", ".join(settings) or "none") + ")"
    pair = ", ".join(f"{q:.2f}" for q in fit.pairwise)
    return f"p = {fit.p:.2f} over {fit.n} settings ({', '.join(settings)}) [{pair}]"


def write_convergence_report(report_dir: str | Path, df: pd.DataFrame, *, orders: Mapping[str, Any],
                             meta: Mapping[str, Any], error_name: str = "position_error") -> dict[str, Path]:
    """``convergence.md``, ``convergence.csv`` and ``pareto.png`` in ``report_dir``; returns their paths."""
    out = Path(report_dir)
    out.mkdir(parents=True, exist_ok=True)
    csv = out / "convergence.csv"
    df.to_csv(csv, index=False)
    if meta.get("config") is not None:  # the sweep as run (settings, reference, families, base config)
        import json

        (out / "config.json").write_text(json.dumps(meta["config"], indent=1, sort_keys=True, default=str))
    png = pareto_figure(df, out / "pareto.png")
    cols = ["setting", "family", "preset", "status", "particle_spacing_m", "particles_per_cell", "dx_m",
            "target_substeps_per_frame", "courant", "stiffness_scaling", "mass_scale", "n_particles",
            "substeps_total", "rollout_s", "pipeline_s", *ERROR_COLUMNS, "pareto"]
    md = [f"# Error against run time: {meta.get('object')} ({meta.get('session')} session)", ""]
    md += [(f"Reference: setting **{meta.get('reference')}** (the finest affordable setting); every error is measured "
           f"against it (definitions: `tasks/verification/convergence.py`). Size normalising the positions: bounding-box "
           f"diagonal {_fmt(meta.get('size_m'))} m. Wall times are the steps' recorded compute seconds on this "
           f"machine ({meta.get('machine', '')}), cold: `rollout_s` the MPM rollout, `pipeline_s` every step of "
           "the object. Other processes shared the cores, so times carry that noise; `substeps_total` and "
           "`n_particles` are the contention-free cost."), ""]
    md += ["## Error-vs-time table", "", markdown_table(df, cols), ""]
    noise = timing_spread(df)
    if noise:
        md += [noise, ""]
    md += [("Deformation metrics (tasks/evaluation/deformation_metrics.py): absolute difference to the reference's score; "
           "`ke_ie_max` the quasi-static check's measure (mass scaling): the largest sum KE / sum IE of the "
           "mass-scaled material over a contact's checked frames (a finger loads the object, past the contact's "
           "first frames), whose limit is mpm.quasi_static_ke_ie_max (empty: no frame checked); "
           "`tracer_drift_m` how far the surface Gaussians left the material by the last frame (m, see "
           "`tracer_drift`)."), "",
           markdown_table(df, ["setting", "mass_scale", "ke_ie_max", "tracer_drift_m",
                               *(f"d_{k}" for k in METRIC_NAMES)]), ""]
    failed = df[df["status"] != "ok"]
    if len(failed):
        md += ["Settings that did not finish: " + "; ".join(f"{r.setting}: {r.note}" for r in failed.itertuples()), ""]
    notes = df[(df["status"] == "ok") & (df["note"].astype(str) != "")]
    if len(notes):
        md += ["Notes: " + "; ".join(f"{r.setting}: {r.note}" for r in notes.itertuples()), ""]
    md += ["## Pareto front", "", "![error against wall time](pareto.png)", "",
           "On the front (position error vs pipeline seconds): "
           + ", ".join(df[df["pareto"]]["setting"]) + ".", ""]
    md += ["## Observed convergence order", ""]
    if not orders:
        md += ["No family refines a single discretisation parameter.", ""]
    md += [(f"{error_name} against the refinement parameter, e ~ C h^p, p the least-squares slope in log-log "
           "space (the reference left out); in brackets the slopes of successive refinements."), ""]
    for fam, o in orders.items():
        md.append(f"- **{fam}** (h = {o['parameter']}): against the reference: {_order_text(o['fit'], o['settings'])}")
        if o.get("self_reference") and o["self_reference"] != meta.get("reference"):
            md.append(f"  against the family's finest member `{o['self_reference']}`: "
                      f"{_order_text(o['self_fit'], o.get('self_settings', []))}")
    md.append("")
    md += ["## Presets", "", preset_summary(df, meta.get("presets", ())), ""]
    md += ["## Not swept", "", *(f"- {note}" for note in (*NOT_SWEPT, *meta.get("notes", ()))), ""]
    (out / "convergence.md").write_text("\n".join(md))
    return {"markdown": out / "convergence.md", "csv": csv, "plot": png}
