"""GPU smoke check: every torch / Warp part of the pipeline on a device against its CPU result, tiny or random weights.

    python -m flows.gpu_check                 # on CUDA; skips cleanly (exit 0) when torch or Warp sees no CUDA device
    python -m flows.gpu_check device=cpu      # the same code on the CPU against a second CPU run (self-check)
    python -m flows.gpu_check parts=[renderer,musiq]

Parts (each built on the CPU from a fixed seed, run on the CPU, copied to ``device`` and run again): the Gaussian
renderer (Warp backend, 200 Gaussians, 2 cameras, 64 px), the MLS-MPM solver (a 1 cm jelly cube falling for 2
frames), the diffusion pipeline (tiny random AnimateDiff + ControlNet components, 8 frames of 32 px, 2 steps, the mask
composite), MUSIQ, AMT-S and the VideoPhy-2 network (tiny random configurations of the published architectures).
One line per part: time on the device, largest difference from the CPU result and its tolerance.  Tolerances allow
float32 reduction order (GPU atomics in the splat and the MPM transfer, cuDNN convolution algorithms, TF32 is switched
off); they are the check's choice, not measured on a GPU here (none exists on this project's machines).  Exit status 1
when a part exceeds its tolerance.
"""
from __future__ import annotations

import copy
import time
from collections.abc import Callable
from dataclasses import dataclass

import hydra
import numpy as np
import torch
from omegaconf import DictConfig

PARTS = ("renderer", "mpm", "diffusion", "musiq", "amt", "videophy")


@dataclass(frozen=True)
class Check:
    part: str
    seconds: float
    difference: float
    tolerance: float
    unit: str

    @property
    def ok(self) -> bool:
        return bool(self.difference <= self.tolerance)

    def line(self, device: str) -> str:
        return (f"{self.part:10s} {device}: {self.seconds:7.2f} s, max |{device} - cpu| = {self.difference:.2e} "
                f"{self.unit} (tolerance {self.tolerance:g}) {'ok' if self.ok else 'FAIL'}")


def _timed(run: Callable[[], np.ndarray]) -> tuple[np.ndarray, float]:
    started = time.perf_counter()
    out = run()
    if torch.cuda.is_available():
        torch.cuda.synchronize()
    return out, time.perf_counter() - started


def _renderer(device: str) -> tuple[Callable[[str], np.ndarray], float, str]:
    from tasks.render.splat import rasterization

    g = torch.Generator().manual_seed(0)
    n = 200
    gaussians = dict(means=torch.rand(n, 3, generator=g) - 0.5, quats=torch.randn(n, 4, generator=g),
                     scales=torch.rand(n, 3, generator=g) * 0.05 + 0.01, opacities=torch.rand(n, generator=g),
                     colors=torch.rand(n, 3, generator=g))
    view = torch.eye(4).repeat(2, 1, 1)
    view[:, 2, 3] = torch.tensor([2.0, 2.5])
    K = torch.tensor([[80.0, 0, 32], [0, 80.0, 32], [0, 0, 1]]).repeat(2, 1, 1)

    def run(on: str) -> np.ndarray:
        args = {k: v.to(on) for k, v in gaussians.items()}
        colors, alphas, _ = rasterization(**args, viewmats=view.to(on), Ks=K.to(on), width=64, height=64,
                                          backend="warp")
        return torch.cat([colors, alphas], -1).cpu().numpy()

    return run, 2e-4, "(colour, alpha in [0, 1]; depth m)"


def _mpm(device: str) -> tuple[Callable[[str], np.ndarray], float, str]:
    from tasks.physics.mpm import Material, MPMSolver

    h = 0.0025
    axis = np.arange(0.0, 0.01 + 1e-9, h)
    positions = np.stack(np.meshgrid(axis, axis, axis + 0.02, indexing="ij"), -1).reshape(-1, 3)
    jelly = Material(name="jelly", model="fixed_corotated", youngs_modulus=5e4, poisson_ratio=0.3, density=1000.0)

    def run(on: str) -> np.ndarray:
        solver = MPMSolver(positions, h ** 3, jelly, config=dict(dx=0.005), device=on)
        for _ in range(2):
            solver.step_frame(1 / 30)
        return solver.positions()

    return run, 1e-5, "m"


def _diffusion(device: str) -> tuple[Callable[[str], np.ndarray], float, str]:
    from tasks.generation.masked_diffusion import DiffusionSettings, build_effect_pipelines, generate_effect
    from tasks.generation.tiny_components import tiny_components

    components = tiny_components(seed=0)
    yy, xx = np.mgrid[:32, :32] / 32
    rgb = np.broadcast_to(np.stack([xx, yy, 0.5 + 0 * xx], -1), (8, 32, 32, 3)).astype(np.float32)
    mask = np.broadcast_to((xx - 0.5) ** 2 + (yy - 0.5) ** 2 < 0.09, (8, 32, 32)).copy()
    depth = np.where(mask, 0.5 + 0.5 * yy, 0.0).astype(np.float32)
    settings = DiffusionSettings(num_inference_steps=2, strength=1.0, window=8, overlap=4)

    def run(on: str) -> np.ndarray:
        moved = copy.deepcopy(components)
        for name in ("vae", "text_encoder", "unet", "motion_adapter", "controlnet"):
            setattr(moved, name, getattr(moved, name).to(on))
        return generate_effect(build_effect_pipelines(moved), rgb, mask, depth, "juice", "", settings)[0]

    return run, 1e-3, "(frames in [0, 1])"


def _musiq(device: str) -> tuple[Callable[[str], np.ndarray], float, str]:
    from tasks.evaluation.musiq import MUSIQ, MusiqConfig, musiq_frame_scores

    torch.manual_seed(0)
    net = MUSIQ(MusiqConfig(token_dim=8, hidden_size=16, mlp_dim=32, num_heads=1, num_layers=2)).eval()
    video = np.random.default_rng(0).integers(0, 256, (2, 96, 128, 3), dtype=np.uint8)
    return lambda on: musiq_frame_scores(video, copy.deepcopy(net).to(on)), 1e-3, "(MOS units)"


def _amt(device: str) -> tuple[Callable[[str], np.ndarray], float, str]:
    from tasks.evaluation.amt import AMT, AmtConfig, amt_midpoint

    torch.manual_seed(0)
    net = AMT(AmtConfig(channels=(8, 12, 16, 20), skip_channels=4, encoder_widths=(8, 16, 24), feature_dim=16,
                        hidden_dim=16, flow_dim=4, corr_dim=8, fc_dim=8)).eval()
    a, b = np.random.default_rng(0).integers(0, 256, (2, 128, 144, 3), dtype=np.uint8)
    return lambda on: amt_midpoint(copy.deepcopy(net).to(on), a, b).astype(float), 1.0, "(8-bit levels: truncation)"


def _videophy(device: str) -> tuple[Callable[[str], np.ndarray], float, str]:
    from tasks.evaluation.videophy import MplugOwlVideo, OwlConfig, keep_layer_norms_fp32, video_pixels

    cfg = {"model_type": "mplug-owl", "num_query_tokens": 4,
           "vision_config": {"hidden_size": 32, "intermediate_size": 64, "num_hidden_layers": 2,
                             "num_attention_heads": 2, "image_size": 28, "patch_size": 14, "layer_norm_eps": 1e-6},
           "visual_abstractor_config": {"hidden_size": 32, "intermediate_size": 64, "num_hidden_layers": 2,
                                        "num_attention_heads": 2, "encoder_hidden_size": 32, "layer_norm_eps": 1e-6},
           "text_config": {"model_type": "llama", "vocab_size": 64, "hidden_size": 32, "intermediate_size": 64,
                           "num_hidden_layers": 2, "num_attention_heads": 2, "num_key_value_heads": 2,
                           "max_position_embeddings": 64, "bos_token_id": 1, "eos_token_id": 2, "pad_token_id": 0}}
    torch.manual_seed(0)
    net = MplugOwlVideo(OwlConfig.from_json(cfg))
    for p in net.parameters():
        torch.nn.init.normal_(p, std=0.5)
    keep_layer_norms_fp32(net.eval())
    video = np.random.default_rng(0).integers(0, 256, (16, 48, 64, 3), dtype=np.uint8)
    ids = [1, 5, 6] + [-2] * 5 + [7, 8]

    def run(on: str) -> np.ndarray:
        moved = copy.deepcopy(net).to(on)
        with torch.inference_mode():
            embeds = moved.prompt_embeddings(ids, video_pixels(video, 8, 28).to(on))
            return moved.language_model(inputs_embeds=embeds).logits.float().cpu().numpy()

    return run, 1e-3, "(logits)"


_BUILDERS = {"renderer": _renderer, "mpm": _mpm, "diffusion": _diffusion, "musiq": _musiq, "amt": _amt,
             "videophy": _videophy}


def run_checks(device: str, parts=PARTS) -> list[Check]:
    """Each part on the CPU, then on ``device``: its time there and its largest difference from the CPU result."""
    unknown = set(parts) - set(PARTS)
    if unknown:
        raise ValueError(f"parts: unknown {sorted(unknown)}; choose from {', '.join(PARTS)}")
    torch.backends.cuda.matmul.allow_tf32 = False
    torch.backends.cudnn.allow_tf32 = False
    checks = []
    for part in parts:
        run, tolerance, unit = _BUILDERS[part](device)
        reference, _ = _timed(lambda: run("cpu"))
        result, seconds = _timed(lambda: run(device))
        difference = float(np.max(np.abs(np.asarray(result, float) - np.asarray(reference, float))))
        checks.append(Check(part, seconds, difference, tolerance, unit))
    return checks


def cuda_missing() -> str | None:
    """Why the CUDA check cannot run here, or None."""
    if not torch.cuda.is_available():
        return f"torch {torch.__version__} sees no CUDA device (a CPU build, or no GPU/driver)"
    import warp as wp

    if wp.get_cuda_device_count() == 0:
        return "Warp sees no CUDA device"
    return None


@hydra.main(version_base="1.3", config_path="../conf", config_name="gpu_check")
def main(cfg: DictConfig) -> None:
    from tasks.render.device import torch_device

    torch_device("cpu")  # thread count
    if cfg.device != "cpu" and (reason := cuda_missing()):
        print(f"gpu_check skipped: {reason}. Run `python -m flows.gpu_check device=cpu` for the CPU self-check.")
        return
    checks = []
    for part in cfg.parts:
        check = run_checks(cfg.device, [part])[0]
        print(check.line(cfg.device), flush=True)
        checks.append(check)
    if not all(c.ok for c in checks):
        raise SystemExit(1)


if __name__ == "__main__":
    main()
