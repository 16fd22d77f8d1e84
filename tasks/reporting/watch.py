"""What a researcher watches in the report: videos of every squeeze, contact sheets, and the control signals drawn
in sync under the videos (paper sec. 3.2-3.3: the G-buffer, the conditions of eq. 6, the effect and its 4D
refinement of eq. 7).

Per object and variant one "stages" video tiles, for every view (rows), the simulated render I, the conditions
(normalised depth, the refined mask M~ in orange), the final composite with the effect, and the renders of the
refined 4D Gaussians.  Per object a contact sheet (rest, peak squeeze, after release; across views) and a control
plot (flexion and force coefficient per finger) with a time cursor that follows whichever video plays.  Pure
functions of artifacts; :mod:`tasks.reporting.report` places what they return.
"""
from __future__ import annotations

import base64
import html
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import matplotlib.pyplot as plt
import numpy as np

from conf.hand import FINGERS
from tasks.core.artifacts import ArtifactError, read_artifact
from tasks.generation.final_video import final_video
from tasks.reporting.media_cache import MediaCache
from tasks.reporting.video import contact_sheet, encode_video, encoder_available, side_by_side

MASK_TINT = np.array([255, 140, 0], np.float32)  # sRGB orange over the depth condition
PLOT_SPAN = (0.09, 0.99)  # the control plot's axes' x extent in figure fraction, where the time cursor runs


@dataclass
class SceneMedia:
    """The media of one object and variant (paths inside the report folder), and what they show."""

    variant: str
    backend: str | None = None
    effect_label: str | None = None
    stages_video: Path | None = None
    final_video: Path | None = None
    loss_plot: Path | None = None
    notes: list[str] = field(default_factory=list)


@dataclass
class ObjectMedia:
    obj: str
    scenes: list[SceneMedia] = field(default_factory=list)
    contact_sheet: Path | None = None
    control_plot: Path | None = None
    plot_span: tuple[float, float] = (0.0, 1.0)  # axes' x extent in figure fraction (for the cursor)
    duration_s: float = 0.0


def conditions_image(normalised_depth: np.ndarray, refined_mask: np.ndarray) -> np.ndarray:
    """uint8 sRGB (..., y, x, 3): the depth condition Norm(D) in grey with the refined mask M~ tinted orange."""
    grey = np.repeat((255.0 * normalised_depth)[..., None], 3, axis=-1).astype(np.float32)
    tinted = np.where(refined_mask[..., None], 0.45 * grey + 0.55 * MASK_TINT, grey)
    return np.clip(tinted, 0, 255).astype(np.uint8)


def _load(ref, names=None):
    if ref is None:
        return None
    try:
        return read_artifact(ref, names=names)
    except ArtifactError:
        return None


def _scene_frames(pair: Mapping[str, Any], refs: Mapping[str, Any]) -> dict[str, np.ndarray] | None:
    """The columns of the stages video (render, conditions, final, refined 4D), each (view, frame, y, x, 3), or
    None when the G-buffer or the conditions cannot be read."""
    g = _load(pair.get("gbuffer"), ["rgb"])
    cond = _load(pair.get("conditions"), ["normalised_depth", "refined_mask"])
    if g is None or cond is None:
        return None
    effect = _load(refs.get("effect"), ["frames"])
    refined = _load(refs.get("appearance_refinement"), ["rgb"])
    columns = {"simulated render I": g["rgb"], "conditions: Norm(D), M~": conditions_image(
        cond["normalised_depth"], cond["refined_mask"]),
        "final composite": final_video(effect, g)}
    if refined is not None and "rgb" in refined:
        columns["refined 4D Gaussians (eq. 7)"] = refined["rgb"]
    return columns


def _stages_video(columns: Mapping[str, np.ndarray], path: Path, fps: float) -> Path:
    n_views = columns["simulated render I"].shape[0]
    tiles = [columns[c][v] for v in range(n_views) for c in columns]
    labels = [f"view {v}: {c}" for v in range(n_views) for c in columns]
    return encode_video(side_by_side(tiles, labels, columns=len(columns)), path, fps)


def _loss_plot(obj: str, variant: str, ref, path: Path) -> Path | None:
    refined = _load(ref, ["loss"])
    if refined is None or "loss" not in refined or not len(refined["loss"]):
        return None
    fig, ax = plt.subplots(figsize=(3.6, 2.2))
    ax.plot(np.arange(1, len(refined["loss"]) + 1), refined["loss"])
    ax.set_xlabel("iteration")
    ax.set_ylabel("sampled L_rec (mean |R - I*|)")
    before, after = refined.attrs.get("loss_before") or {}, refined.attrs.get("loss_after") or {}

    def fmt(x):
        return "-" if x is None else f"{x:.4f}"

    ax.set_title(f"{obj} [{variant}]: eq. 7; L_rec train {fmt(before.get('train'))} -> {fmt(after.get('train'))}, "
                 f"held-out {fmt(before.get('held_out'))} -> {fmt(after.get('held_out'))}", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def scene_media(obj: str, variant: str, pair: Mapping[str, Any], backend_refs: Mapping[str, Mapping[str, Any]],
                out_dir: Path, fps: float, cache: MediaCache | None = None) -> SceneMedia | None:
    """Encode the stages video (rows: views; columns: render, conditions, final, refined 4D) and the final
    composite video of view 0, plus the eq. 7 loss curve, for one object and variant (first backend); media
    already in ``cache`` (same input digests, parameters and code) are reused, not encoded again."""
    cache = cache or MediaCache(None)
    if pair.get("gbuffer") is None or pair.get("conditions") is None:
        return None
    backend, refs = next(iter(backend_refs.items()), (None, {}))
    media = SceneMedia(variant=variant, backend=backend)
    effect = _load(refs.get("effect"), [])
    if effect is not None:
        media.effect_label = effect.attrs.get("label")
        if effect.attrs.get("skipped"):
            media.notes.append(f"effect skipped: {effect.attrs['skipped']}")
    inputs = {"gbuffer": pair["gbuffer"], "conditions": pair["conditions"], "effect": refs.get("effect"),
              "appearance_refinement": refs.get("appearance_refinement"), "display_video": refs.get("display_video")}
    params = {"obj": obj, "variant": variant, "fps": fps, "h264": encoder_available("libx264")}  # else WebP
    keys = {kind: cache.key(kind, params, inputs) for kind in ("stages_video", "final_video")}
    columns = None
    if cache.lookup(keys["stages_video"]) is None or (cache.lookup(keys["final_video"]) is None
                                                      and refs.get("display_video") is None):
        columns = _scene_frames(pair, refs)
        if columns is None:
            return None
    media.stages_video = cache.get(out_dir / f"{obj}_{variant}_stages.mp4", keys["stages_video"],
                                   lambda p: _stages_video(columns, p, fps))
    media.final_video = cache.get(out_dir / f"{obj}_{variant}_final.mp4", keys["final_video"],
                                  lambda p: _final_video(refs.get("display_video"), columns, p, fps))
    ref = refs.get("appearance_refinement")
    media.loss_plot = cache.get(out_dir / f"{obj}_{variant}_refinement.png",
                                cache.key("loss_plot", {"obj": obj, "variant": variant}, {"appearance_refinement": ref}),
                                lambda p: _loss_plot(obj, variant, ref, p))
    return media


def watched_video(display_ref) -> tuple[np.ndarray, list[str]] | None:
    """The display step's frames (view, frame, y, x, 3) uint8 sRGB (orbit views at the video resolution, close-up
    last, the hand drawn) and the views' names, or None when it was not made."""
    display = _load(display_ref, ["frames"])
    if display is None or "frames" not in display:
        return None
    return display["frames"], list(display.attrs.get("views") or [f"view {v}" for v in range(len(display["frames"]))])


def _final_video(display_ref, columns: Mapping[str, np.ndarray] | None, path: Path, fps: float) -> Path:
    """The watched final video: view 0 beside the close-up at the video resolution with the hand (display step),
    else the final composite of view 0 at the G-buffer resolution."""
    watched = watched_video(display_ref)
    if watched is None:
        return encode_video(columns["final composite"][0], path, fps)
    frames, names = watched
    shown = [0, len(frames) - 1] if len(frames) > 1 else [0]
    return encode_video(side_by_side([frames[v] for v in shown], [names[v] for v in shown]), path, fps)


def moments(strain: np.ndarray, event: Mapping[str, Any], frame_index: np.ndarray) -> dict[str, int]:
    """Rendered-frame indices of rest (0), peak squeeze (max strain) and after release (the last frame, or the
    last frame before the fingers let go when nothing was released)."""
    peak_sim = int(np.argmax(strain.max(axis=1)))
    after = len(frame_index) - 1
    return {"rest": 0, "peak squeeze": int(np.argmin(np.abs(frame_index - peak_sim))),
            ("after release" if event.get("crossed") else "end"): after}


def _contact_sheet(first: Mapping[str, Any], path: Path) -> Path | None:
    """Rows views, columns rest / peak squeeze / after release, of the final video of one variant."""
    g = _load(first.get("gbuffer"), ["rgb", "frame_index"])
    rollout = _load(first.get("mpm_rollout"), ["squeeze_strain"])
    backend_refs = next(iter(first.get("backends", {}).values()), {})
    watched = watched_video(backend_refs.get("display_video"))
    if watched is not None:  # the watched video: every view and the close-up, with the hand
        final, names = watched
    else:
        final = final_video(_load(backend_refs.get("effect"), ["frames"]), g)
        names = [f"view {v}" for v in range(final.shape[0])]
    picks = moments(rollout["squeeze_strain"], rollout.attrs.get("threshold_event") or {}, g["frame_index"])
    sheet = contact_sheet(final[:, list(picks.values())], names, list(picks))
    plt.imsave(path, sheet)
    return path


def overview_sheet(refs: Mapping[str, Mapping[str, Any]], path: Path, view: int = 1, tile_px: int = 192
                   ) -> Path | None:
    """One row per object, columns rest / peak squeeze / after release (or end): orbit view ``view`` of the watched
    video (hand visible) of each object's first variant and backend, tiles resized to ``tile_px``."""
    rows, labels = [], []
    for obj, obj_refs in refs.items():
        variant = next(iter(obj_refs.get("variants", {}).values()), None)
        if variant is None:
            continue
        backend = next(iter(variant.get("backends", {}).values()), {})
        watched = watched_video(backend.get("display_video"))
        g = _load(variant.get("gbuffer"), ["frame_index"])
        rollout = _load(variant.get("mpm_rollout"), ["squeeze_strain"])
        if watched is None or g is None or rollout is None:
            continue
        frames = watched[0][min(view, len(watched[0]) - 1)]
        picks = list(moments(rollout["squeeze_strain"], rollout.attrs.get("threshold_event") or {},
                             g["frame_index"]).values())
        rows.append([cv2.resize(frames[f], (tile_px, tile_px), interpolation=cv2.INTER_AREA) for f in picks])
        labels.append(obj)
    if not rows:
        return None
    sheet = contact_sheet(np.asarray(rows), labels, ["rest", "peak squeeze", "after release / end"])
    plt.imsave(path, sheet)
    return path


def object_media(obj: str, obj_refs: Mapping[str, Any], out_dir: Path, cache: MediaCache | None = None,
                 scenes_only: bool = False) -> ObjectMedia | None:
    """All media of one object: every variant's scene media, the contact sheet of the first variant, the
    synchronised control plot (reused from ``cache`` when already made from the same artifacts).  With
    ``scenes_only`` the variants' scene media alone (:func:`tasks.reporting.report.cache_scene_media`)."""
    cache = cache or MediaCache(None)
    variants = obj_refs.get("variants", {})
    media = ObjectMedia(obj)
    fps = None
    first = None  # the first variant that was rendered (a variant whose simulation failed has no G-buffer)
    for variant, vrefs in variants.items():
        g = _load(vrefs.get("gbuffer"), ["time"])
        if g is None:
            continue
        first = vrefs if first is None else first
        times = g["time"]
        fps = 1.0 / float(times[1] - times[0]) if len(times) > 1 else 1.0
        media.duration_s = float(len(times) / fps)
        scene = scene_media(obj, variant, {**obj_refs, **vrefs}, vrefs.get("backends", {}), out_dir, fps, cache)
        if scene is not None:
            media.scenes.append(scene)
    if not media.scenes:
        return None
    if scenes_only:
        return media
    first_backend = next(iter(first.get("backends", {}).values()), {})
    sheet_inputs = {"gbuffer": first.get("gbuffer"), "mpm_rollout": first.get("mpm_rollout"),
                    "effect": first_backend.get("effect"), "display_video": first_backend.get("display_video")}
    media.contact_sheet = cache.get(out_dir / f"{obj}_contact_sheet.png",
                                    cache.key("contact_sheet", {"obj": obj}, sheet_inputs),
                                    lambda p: _contact_sheet(first, p))
    signal_inputs = {k: obj_refs.get(k) for k in ("signal_smoothing", "force_coefficients")}
    media.control_plot = cache.get(out_dir / f"{obj}_signals.png",
                                   cache.key("control_plot", {"obj": obj, "duration_s": media.duration_s},
                                             signal_inputs),
                                   lambda p: control_plot(obj, obj_refs, p, media.duration_s))
    media.plot_span = PLOT_SPAN if media.control_plot else (0.0, 1.0)
    return media


def control_plot(obj: str, obj_refs: Mapping[str, Any], path: Path, duration_s: float) -> Path | None:
    """Flexion and force coefficient per finger over the rendered clip's time span, the axes spanning
    :data:`PLOT_SPAN` of the figure's width; returns the path (None without the signals)."""
    frames = _load(obj_refs.get("signal_smoothing"), ["time", "flexion"])
    forces = _load(obj_refs.get("force_coefficients"), ["force_coefficients"])
    if frames is None or forces is None:
        return None
    t = frames["time"] - frames["time"][0]
    fig, axes = plt.subplots(2, 1, figsize=(7.2, 2.8), sharex=True)
    for k, finger in enumerate(FINGERS):
        axes[0].plot(t, frames["flexion"][:, k], label=finger, lw=1)
        axes[1].plot(t, forces["force_coefficients"][:, k], lw=1)
    axes[0].set_ylabel("flexion (1)", fontsize=8)
    axes[1].set_ylabel("force coeff. (1)", fontsize=8)
    axes[1].set_xlabel("time (s)", fontsize=8)
    axes[0].legend(fontsize=6, ncol=5, loc="upper left")
    for ax in axes:
        ax.set_xlim(0.0, duration_s)
        ax.tick_params(labelsize=7)
    fig.subplots_adjust(left=PLOT_SPAN[0], right=PLOT_SPAN[1], top=0.97, bottom=0.16, hspace=0.12)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _data_uri(path: Path, mime: str) -> str:
    return f"data:{mime};base64," + base64.b64encode(Path(path).read_bytes()).decode()


def video_tag(path: Path, obj: str, width: int, controls: bool = True) -> str:
    """A looping, muted, autoplaying <video> embedded in the page (plays offline), tied to its object's cursor."""
    return (f'<video class="sync" data-obj="{html.escape(obj)}" width="{width}" autoplay muted loop playsinline'
            f'{" controls" if controls else ""} src="{_data_uri(path, "video/mp4")}"></video>')


def overview_html(media: list[ObjectMedia], labels: Mapping[str, str]) -> str:
    """One row per object, the variants side by side (the watched video: view 0 and the close-up, with the hand)."""
    variants = list(dict.fromkeys(s.variant for m in media for s in m.scenes))
    head = "".join(f"<th>{html.escape(labels.get(v, v))}</th>" for v in variants)
    rows = []
    for m in media:
        by = {s.variant: s for s in m.scenes}
        cells = "".join(f"<td>{video_tag(by[v].final_video, m.obj, 440, controls=False)}</td>" if v in by
                        and by[v].final_video else "<td>-</td>" for v in variants)
        rows.append(f"<tr><th>{html.escape(m.obj)}</th>{cells}</tr>")
    return f"<table class='overview'><tr><th>object</th>{head}</tr>{''.join(rows)}</table>"


def object_html(m: ObjectMedia, labels: Mapping[str, str]) -> str:
    """An object's media block: contact sheet, then per variant the stages video with the control plot and its
    time cursor underneath, and the refinement loss."""
    out = []
    if m.contact_sheet:
        out.append(f'<p><img alt="{html.escape(m.obj)} contact sheet" style="max-width:100%" '
                   f'src="{_data_uri(m.contact_sheet, "image/png")}"></p>')
    for s in m.scenes:
        label = labels.get(s.variant, s.variant)
        effect = f"; effect: {html.escape(s.effect_label)}" if s.effect_label else ""
        out.append(f"<h4>{html.escape(label)}{effect}</h4>")
        if s.notes:
            out.append("<p>" + html.escape("; ".join(s.notes)) + "</p>")
        out.append(video_tag(s.stages_video, m.obj, 760))
        if m.control_plot:
            x0, x1 = m.plot_span
            out.append(f'<div class="plot" data-obj="{html.escape(m.obj)}" data-x0="{x0:.4f}" data-x1="{x1:.4f}" '
                       f'data-duration="{m.duration_s:.4f}"><img src="{_data_uri(m.control_plot, "image/png")}">'
                       f'<div class="cursor"></div></div>')
        if s.loss_plot:
            out.append(f'<img alt="refinement loss" src="{_data_uri(s.loss_plot, "image/png")}">')
    return "\n".join(out)


# The cursor of every control plot follows the last video of its object that advanced.
SYNC_SCRIPT = """<script>
document.querySelectorAll('video.sync').forEach(function (v) {
  v.addEventListener('timeupdate', function () {
    document.querySelectorAll('.plot[data-obj="' + v.dataset.obj + '"]').forEach(function (p) {
      var f = Math.min(1, v.currentTime / parseFloat(p.dataset.duration));
      var x = parseFloat(p.dataset.x0) + f * (parseFloat(p.dataset.x1) - parseFloat(p.dataset.x0));
      p.querySelector('.cursor').style.left = (100 * x) + '%';
    });
  });
});
</script>"""
STYLE = (".overview video{display:block}.plot{position:relative;display:inline-block;width:760px}"
         ".plot img{width:100%;display:block}.cursor{position:absolute;top:0;bottom:0;width:2px;"
         "background:#d00;left:0}")
