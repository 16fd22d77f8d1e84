"""LLM evaluation of one object, variant and effect backend (paper sec. 4.1.4; Table 1's LLM columns): a vision
LLM scores the final video of view 0 together with a plot of the squeezing controls on visual quality, motion
realism and motion consistency (1-5), through :func:`tasks.evaluation.llm_judge.judge_video`.  Without
``llm_judge.url`` the step asks nothing and records why."""
from __future__ import annotations

import numpy as np

from conf.hand import FINGERS
from tasks.core.step import artifact_step
from tasks.evaluation.llm_judge import JudgeConfig, judge_video
from tasks.generation.final_video import final_video


def controls_image(time_s: np.ndarray, flexion: np.ndarray, force_coefficients: np.ndarray) -> np.ndarray:
    """uint8 sRGB (y, x, 3) plot of the flexion (top) and the force coefficient (bottom) per finger over time."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 1, figsize=(6.4, 3.2), dpi=100, sharex=True)
    for k, finger in enumerate(FINGERS):
        axes[0].plot(time_s, flexion[:, k], label=finger)
        axes[1].plot(time_s, force_coefficients[:, k])
    axes[0].set_ylabel("flexion")
    axes[1].set_ylabel("force coefficient")
    axes[1].set_xlabel("time (s)")
    axes[0].legend(fontsize=7, ncol=5)
    fig.tight_layout()
    fig.canvas.draw()
    image = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    plt.close(fig)
    return image


@artifact_step("llm_evaluation", inputs=("effect", "gbuffer", "signal_smoothing", "force_coefficients"),
               reads=("llm_judge", "object.display_name"), outputs=())
def llm_evaluation_step(inputs, params):
    """Table 1's LLM scores of one scene, or the reason they were not computed."""
    judge = params["llm_judge"]
    if not judge["url"]:
        return {}, {"scores": None, "reason": "not computed: no vision LLM endpoint configured (llm_judge.url)"}
    effect, g = inputs["effect"], inputs["gbuffer"]
    final = final_video(effect, g)[0]
    frames = inputs["signal_smoothing"]
    image = controls_image(frames["time"] - frames["time"][0], frames["flexion"],
                           inputs["force_coefficients"]["force_coefficients"])
    scores = judge_video(final, image, params["object.display_name"], g.attrs.get("released_material") or "none",
                         JudgeConfig(**judge))
    return {}, {"scores": scores.model_dump(), "reason": None, "model": judge["model"]}
