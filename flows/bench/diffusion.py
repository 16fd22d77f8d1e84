"""Cost of the paper's video generator on this machine, with random weights of the real sizes (no download).

    python -m flows.bench.diffusion                          # 256 and 512 px, float32 and bfloat16
    python -m flows.bench.diffusion sizes=[256] dtypes=[float32] frames_timed=[1]

Per size and dtype: one denoising step of the real ``AnimateDiffVideoToVideoControlNetPipeline`` (SD-1.5 UNet +
AnimateDiff v1-5-2 motion adapter + depth ControlNet, classifier-free guidance) is timed on ``frames_timed`` frames,
and the step's FLOPs are counted exactly (fake tensors) for those frames and for the ``window``-frame window.  The
window's time is the largest timed run scaled by the FLOP ratio; its peak memory is the weights plus the
activations extrapolated linearly in frames from the two timed runs.  Then the default grid's diffusion rows:
clips x (steps x step time of the padded sequence + VAE encode/decode of every frame), the padded sequence's step
scaled from the window's by frames.  GPU lines are estimates (counted FLOPs / (datasheet peak x assumed
utilization)), never measurements.  Config: ``conf/study/bench_diffusion.yaml`` (keys:
:class:`conf.study.schema.DiffusionBenchConfig`).
"""
from __future__ import annotations

import gc
import os

import hydra
from omegaconf import DictConfig

from conf.study.schema import register_study_configs

register_study_configs()

DTYPES = ("float32", "bfloat16", "float16")


def check_config(cfg: DictConfig) -> None:
    """One ``input error`` line naming the key and the fix, before any model is built."""
    for bad in (d for d in cfg.dtypes if d not in DTYPES):
        raise SystemExit(f"input error: dtypes: unknown dtype {bad!r}; one of {list(DTYPES)}")
    for key in ("sizes", "frames_timed"):
        if not cfg[key]:
            raise SystemExit(f"input error: {key} is empty; give at least one value, e.g. {key}=[1]")
        for bad in (v for v in cfg[key] if not v >= 1):
            raise SystemExit(f"input error: {key} must be >= 1, got {bad}")
    for bad in (s for s in cfg.sizes if s % 8):
        raise SystemExit(f"input error: sizes: {bad} px is not a multiple of 8 (the VAE's factor); e.g. {bad - bad % 8}")
    if max(cfg.frames_timed) > cfg.window:
        raise SystemExit(f"input error: frames_timed {list(cfg.frames_timed)} exceeds window={cfg.window}; "
                         "time fewer frames than the window")
    if not 0 < cfg.gpus.utilization <= 1:
        raise SystemExit(f"input error: gpus.utilization must be in (0, 1], got {cfg.gpus.utilization}")
    g = cfg.grid
    if not (g.clips >= 1 and g.frames >= 1 and int(g.steps * g.strength) >= 1 and 0 < g.strength <= 1
            and 0 <= g.overlap < cfg.window):
        raise SystemExit("input error: grid needs clips >= 1, frames >= 1, 0 < strength <= 1, steps x strength >= 1 "
                         f"and 0 <= overlap < window; got {dict(g)} with window={cfg.window}")


def _extrapolate(timed: dict[int, dict], flops: dict[int, int], window: int) -> tuple[float, float]:
    """(seconds, peak GB) of a window-frame step from the timed runs: seconds scaled by the FLOP ratio from the
    largest run; activations (peak minus the memory before the step) linear in frames through the two largest."""
    frames = sorted(timed)
    top = frames[-1]
    seconds = timed[top]["seconds"] * flops[window] / flops[top]
    act = {f: timed[f]["rss_peak_gb"] - timed[f]["rss_before_gb"] for f in frames}
    slope = (act[top] - act[frames[-2]]) / (top - frames[-2]) if len(frames) > 1 else act[top] / top
    slope = max(0.0, slope)  # sampling noise can make the larger run's peak the smaller
    return seconds, timed[top]["rss_before_gb"] + act[top] + slope * (window - top)


def _grid_line(cfg: DictConfig, name: str, step_window_s: float, encode_s: float, decode_s: float) -> str:
    from tasks.generation.masked_diffusion import temporal_windows

    g = cfg.grid
    padded = temporal_windows(g.frames, cfg.window, g.overlap)[-1][1]
    steps = int(g.steps * g.strength)
    clip = steps * step_window_s * padded / cfg.window + padded * (encode_s + decode_s)
    return (f"  {name}: one {cfg.window}-frame step {step_window_s:.3g} s; per clip ({g.frames} frames padded to "
            f"{padded}, {steps} steps{', VAE both ways' if cfg.vae else ', VAE not timed'}) {clip:.4g} s; {g.clips} clips {clip * g.clips / 3600:.3g} h")


@hydra.main(version_base="1.3", config_path="../../conf", config_name="study/bench_diffusion")
def main(cfg: DictConfig) -> None:
    check_config(cfg)
    import torch

    from tasks.generation.step_cost import (
        sd15_video_models,
        step_flops,
        time_step,
        time_vae,
        vae_flops,
        video_pipeline,
    )

    torch.set_num_threads(int(os.environ.get("VIRSQUEEZER_TORCH_THREADS", cfg.threads)))
    print(f"torch threads {torch.get_num_threads()}, {os.cpu_count()} cores; wall seconds of single runs "
          "(no repetition: read them as +-30 % on a shared machine)", flush=True)
    for dtype_name in cfg.dtypes:
        models = sd15_video_models(getattr(torch, dtype_name))
        params = models.parameters_m()
        print(f"[{dtype_name}] parameters (M): " + ", ".join(f"{k} {v:.0f}" for k, v in params.items()), flush=True)
        pipe = video_pipeline(models)
        for size in cfg.sizes:
            frames = sorted(set(cfg.frames_timed) | {cfg.window})
            flops = {f: sum(step_flops(models, f, size)) for f in frames}
            control16, unet16 = step_flops(models, cfg.window, size)
            timed = {}
            for f in sorted(cfg.frames_timed):
                timed[f] = time_step(pipe, f, size)
                print(f"  {size} px {dtype_name}, {f} frame(s): {timed[f]['seconds']:.1f} s, "
                      f"{flops[f] / 1e12:.2f} TFLOP ({flops[f] / timed[f]['seconds'] / 1e9:.0f} GFLOPS), "
                      f"RSS {timed[f]['rss_before_gb']:.1f} -> peak {timed[f]['rss_peak_gb']:.1f} GB", flush=True)
                gc.collect()
            seconds, peak = _extrapolate(timed, flops, cfg.window)
            print(f"  {size} px {dtype_name}, {cfg.window}-frame window step: {flops[cfg.window] / 1e12:.2f} TFLOP "
                  f"(ControlNet {control16 / 1e12:.2f}, motion UNet {unet16 / 1e12:.2f}); extrapolated "
                  f"{seconds:.0f} s, peak RSS ~{peak:.1f} GB", flush=True)
            encode_s = decode_s = 0.0
            if cfg.vae:
                encode_s, decode_s = time_vae(models, size)
                enc_f, dec_f = vae_flops(models, size)
                print(f"  {size} px {dtype_name}, VAE per frame: encode {encode_s:.1f} s ({enc_f / 1e9:.0f} GFLOP), "
                      f"decode {decode_s:.1f} s ({dec_f / 1e9:.0f} GFLOP)", flush=True)
            print(_grid_line(cfg, f"grid diffusers row at {size} px {dtype_name} on this CPU", seconds, encode_s,
                             decode_s), flush=True)
            for gpu, tflops in cfg.gpus.peaks.items():
                rate = tflops * 1e12 * cfg.gpus.utilization
                vae_rate = (enc_f + dec_f) / rate if cfg.vae else 0.0
                print(_grid_line(cfg, f"estimate {gpu} at {cfg.gpus.utilization:.0%} of peak, {size} px",
                                 flops[cfg.window] / rate, vae_rate, 0.0), flush=True)
        del pipe, models
        gc.collect()


if __name__ == "__main__":
    main()
