"""The one builder of the diffusion components used by the effect generation (paper sec. 3.3).

The paper conditions AnimateDiff (a motion adapter on Stable Diffusion 1.5) and Stable Diffusion img2img with a
depth ControlNet. Their seven components (vae, text_encoder, tokenizer, unet, motion_adapter, controlnet,
scheduler) are loaded here, once, from local folders only, and injected into the pipelines (diffusers' design:
components are built outside the pipeline call). Nothing is downloaded: folders are checked without loading,
missing models are reported with the command that fetches them on a machine with internet, the hub is switched
offline and every loader runs with `local_files_only=True`; single-file checkpoints need a local diffusers-format
config folder because `from_single_file` otherwise fetches configs (diffusers issues #8752, #7902).
"""

import json
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import huggingface_hub.constants
import torch
from diffusers import (
    AutoencoderKL,
    ControlNetModel,
    DDIMScheduler,
    MotionAdapter,
    StableDiffusionPipeline,
    UNet2DConditionModel,
)
from transformers import CLIPTextModel, CLIPTokenizer

from tasks.core.digest_cache import file_digest
from tasks.core.hub import HubSource

CONFIG_NAMES = ("model_index.json", "config.json", "scheduler_config.json")
# what `from_pretrained` reads: configs, tokenizer files, full-precision safetensors (not the fp16 variants, the
# original-format single files or the safety checker, which add GBs)
_DIFFUSERS_FILES = ("*.json", "*.txt", "*model.safetensors")


@dataclass(frozen=True)
class ModelWeights:
    """Where one model lives inside `DiffusionWeights.folder`.

    `subfolder` holds a diffusers-format folder (what `save_pretrained` / the hub repo contain). Alternatively
    `single_file` names one original-format checkpoint (.safetensors/.ckpt) and `single_file_config` the local
    diffusers-format config folder describing it; both are relative to the weights folder or absolute.
    """

    subfolder: str
    single_file: str | None = None
    single_file_config: str | None = None


@dataclass(frozen=True)
class DiffusionWeights:
    """The local weights of the three models the paper's generator combines (sec. 3.3)."""

    folder: str
    stable_diffusion: ModelWeights = field(default_factory=lambda: ModelWeights("stable-diffusion"))
    motion_adapter: ModelWeights = field(default_factory=lambda: ModelWeights("motion-adapter"))
    controlnet_depth: ModelWeights = field(default_factory=lambda: ModelWeights("controlnet-depth"))


@dataclass(frozen=True)
class MissingModel:
    """One model that cannot be loaded: what it is, the hub repository that has it, the path found wanting and
    why, and the diffusers-format folder a download should fill (`<folder>/<subfolder>`, used by default)."""

    model: str
    repo: str
    expected: Path
    problem: str
    fetch_to: Path
    command: str  # the `hf download` command that fills fetch_to


@dataclass
class DiffusionComponents:
    """The seven components shared by the AnimateDiff, ControlNet img2img and text-to-video pipelines."""

    vae: AutoencoderKL
    text_encoder: CLIPTextModel
    tokenizer: CLIPTokenizer
    unet: UNet2DConditionModel
    motion_adapter: MotionAdapter
    controlnet: ControlNetModel
    scheduler: DDIMScheduler


class MissingWeightsError(ValueError):
    """Raised by `load_components` when `check_weights` finds missing models; the message says how to fetch them."""


@dataclass(frozen=True)
class _Part:
    """One folder of a diffusers-format model: its config files (alternatives separated by '|') and weight stem."""

    path: str
    configs: tuple[str, ...]
    weight_stem: str | None = None


@dataclass(frozen=True)
class _ModelSpec:
    """A model of the generator: its name in messages, an example hub repo, its folder layout."""

    key: str
    name: str
    source: HubSource
    parts: tuple[_Part, ...]

    @property
    def repo(self) -> str:
        return self.source.repo


_MODEL_SPECS = (
    _ModelSpec(
        "stable_diffusion",
        "an SD-1.5 base",
        HubSource("stable-diffusion-v1-5/stable-diffusion-v1-5", include=_DIFFUSERS_FILES,
                  exclude=("safety_checker/*",)),
        (
            _Part("", ("model_index.json",)),
            _Part("unet", ("config.json",), "diffusion_pytorch_model"),
            _Part("vae", ("config.json",), "diffusion_pytorch_model"),
            _Part("text_encoder", ("config.json",), "model"),
            _Part("tokenizer", ("tokenizer.json|vocab.json+merges.txt",)),
            _Part("scheduler", ("scheduler_config.json",)),
        ),
    ),
    _ModelSpec(
        "motion_adapter",
        "an AnimateDiff motion adapter",
        HubSource("guoyww/animatediff-motion-adapter-v1-5-2", include=_DIFFUSERS_FILES),
        (_Part("", ("config.json",), "diffusion_pytorch_model"),),
    ),
    _ModelSpec(
        "controlnet_depth",
        "a depth ControlNet",
        HubSource("lllyasviel/control_v11f1p_sd15_depth", include=_DIFFUSERS_FILES),
        (_Part("", ("config.json",), "diffusion_pytorch_model"),),
    ),
)
_TOKENIZER_EXTRAS = ("tokenizer_config.json", "special_tokens_map.json", "added_tokens.json")


def _resolve(folder: str, path: str) -> Path:
    """`path` relative to the weights folder, or absolute."""
    return Path(folder).expanduser() / Path(path).expanduser()


def _present_alternative(directory: Path, alternatives: str) -> list[Path] | None:
    """The files of the first satisfied alternative in 'a.json|b.json+c.txt', or None if none is complete."""
    for alternative in alternatives.split("|"):
        files = [directory / name for name in alternative.split("+")]
        if all(file.is_file() for file in files):
            return files
    return None


def _weight_files(directory: Path, stem: str) -> list[Path]:
    """The weight files `from_pretrained` reads for `stem`: safetensors before bin, single file or sharded index."""
    for suffix in ("safetensors", "bin"):
        single = directory / f"{stem}.{suffix}"
        if single.is_file():
            return [single]
        index = directory / f"{stem}.{suffix}.index.json"
        if index.is_file():
            shards = sorted(set(json.loads(index.read_text())["weight_map"].values()))
            return [index] + [directory / shard for shard in shards]
    return []


def _part_problem(root: Path, part: _Part, with_weights: bool) -> str | None:
    """Why a diffusers-format part cannot load (absent config or weight file), or None."""
    directory = root / part.path
    for alternatives in part.configs:
        if _present_alternative(directory, alternatives) is None:
            return f"no {alternatives.replace('|', ' or ')} in {part.path or '.'}/"
    if with_weights and part.weight_stem is not None:
        files = _weight_files(directory, part.weight_stem)
        if not files or not all(file.is_file() for file in files):
            return f"no {part.weight_stem}.safetensors (or .bin) in {part.path or '.'}/"
    return None


def _model_problem(weights: DiffusionWeights, spec: _ModelSpec) -> tuple[Path, str] | None:
    """(expected path, problem) for one model, or None when its files are all present."""
    source: ModelWeights = getattr(weights, spec.key)
    if source.single_file is not None:
        checkpoint = _resolve(weights.folder, source.single_file)
        if not checkpoint.is_file():
            return checkpoint, "single-file checkpoint absent"
        if source.single_file_config is None:
            return checkpoint, "single-file checkpoint needs single_file_config (a local diffusers config folder)"
        root, with_weights = _resolve(weights.folder, source.single_file_config), False
    else:
        root, with_weights = _resolve(weights.folder, source.subfolder), True
    if not root.is_dir():
        return root, "folder absent"
    for part in spec.parts:
        problem = _part_problem(root, part, with_weights)
        if problem is not None:
            return root, problem
    return None


def check_weights(weights: DiffusionWeights) -> list[MissingModel]:
    """The models of `weights` that cannot be loaded, found by inspecting files only (nothing is loaded).

    Diffusers format: the config files (model_index.json, config.json, scheduler_config.json, tokenizer files)
    and the weight files `from_pretrained` would read. Single file: the checkpoint plus its config folder.
    """
    missing = []
    for spec in _MODEL_SPECS:
        found = _model_problem(weights, spec)
        if found is not None:
            fetch_to = _resolve(weights.folder, getattr(weights, spec.key).subfolder)
            missing.append(MissingModel(spec.name, spec.repo, found[0], found[1], fetch_to,
                                        spec.source.command(fetch_to)))
    return missing


def missing_weights_message(missing: list[MissingModel]) -> str:
    """One header line plus one line per missing model: what it is, where it was expected, how to fetch it."""
    lines = [
        "Diffusion weights missing (nothing is downloaded at run time); on a machine with internet run the command "
        "shown (huggingface_hub's `hf` CLI), then copy the folder it fills to the same path here "
        "(docs/tutorials/diffusion-weights.md, 'Download'):"
    ]
    for model in missing:
        lines.append(f"  {model.model} at {model.expected} ({model.problem}): {model.command}")
    return "\n".join(lines)


def file_sha256(path: Path) -> str:
    """SHA-256 of a file's bytes, remembered across runs by (path, size, mtime) (:mod:`tasks.core.digest_cache`):
    the ~7 GB of weights are read once per version, not on every run."""
    return file_digest(path)


def _part_files(root: Path, part: _Part, with_weights: bool) -> list[Path]:
    """Every file a loader reads for one part: configs, tokenizer extras present, weight files."""
    directory = root / part.path
    files = [file for alternatives in part.configs for file in _present_alternative(directory, alternatives)]
    if part.path == "tokenizer":
        files += [directory / name for name in _TOKENIZER_EXTRAS if (directory / name).is_file()]
    if with_weights and part.weight_stem is not None:
        files += _weight_files(directory, part.weight_stem)
    return files


def weights_identity(weights: DiffusionWeights) -> dict:
    """What the generated frames depend on, for the cache key: per model its configs and file digests.

    Returns {model key: {"format": "diffusers" | "single_file", "configs": {relative path: parsed JSON},
    "sha256": {relative path: hex digest}}}: model_index.json, config.json and scheduler_config.json are parsed
    (readable keys), every other file read (weights, tokenizer files, shard indexes) is hashed.
    Raises MissingWeightsError when `check_weights` finds missing models.
    """
    missing = check_weights(weights)
    if missing:
        raise MissingWeightsError(missing_weights_message(missing))
    identity = {}
    for spec in _MODEL_SPECS:
        source: ModelWeights = getattr(weights, spec.key)
        single = source.single_file is not None
        root = _resolve(weights.folder, source.single_file_config if single else source.subfolder)
        files = [file for part in spec.parts for file in _part_files(root, part, not single)]
        configs = {str(f.relative_to(root)): json.loads(f.read_text()) for f in files if f.name in CONFIG_NAMES}
        digests = {str(f.relative_to(root)): file_sha256(f) for f in files if f.name not in CONFIG_NAMES}
        if single:
            digests["<single_file>"] = file_sha256(_resolve(weights.folder, source.single_file))
        identity[spec.key] = {
            "format": "single_file" if single else "diffusers",
            "configs": configs,
            "sha256": digests,
        }
    return identity


def _hub_offline() -> None:
    """Switch the Hugging Face hub off for this process: environment (for libraries imported later) and the
    already-imported huggingface_hub constant that its HTTP session checks before every request."""
    os.environ["HF_HUB_OFFLINE"] = "1"
    os.environ["TRANSFORMERS_OFFLINE"] = "1"
    os.environ["HF_HUB_DISABLE_TELEMETRY"] = "1"
    huggingface_hub.constants.HF_HUB_OFFLINE = True


def _animatediff_scheduler(config: dict) -> DDIMScheduler:
    """DDIM as AnimateDiff's diffusers recipe sets it (linear betas, no clipping, linspace timesteps, offset 1)."""
    return DDIMScheduler.from_config(
        config, beta_schedule="linear", clip_sample=False, timestep_spacing="linspace", steps_offset=1
    )


def _load_stable_diffusion(weights: DiffusionWeights, dtype: torch.dtype) -> dict:
    """vae, text_encoder, tokenizer, unet and scheduler of the SD-1.5 base, from a folder or a single file."""
    source = weights.stable_diffusion
    if source.single_file is not None:
        pipe = StableDiffusionPipeline.from_single_file(
            str(_resolve(weights.folder, source.single_file)),
            config=str(_resolve(weights.folder, source.single_file_config)),
            local_files_only=True,
            torch_dtype=dtype,
            safety_checker=None,
            feature_extractor=None,
        )
        return {
            "vae": pipe.vae,
            "text_encoder": pipe.text_encoder,
            "tokenizer": pipe.tokenizer,
            "unet": pipe.unet,
            "scheduler": _animatediff_scheduler(pipe.scheduler.config),
        }
    root = str(_resolve(weights.folder, source.subfolder))
    return {
        "vae": AutoencoderKL.from_pretrained(root, subfolder="vae", torch_dtype=dtype, local_files_only=True),
        "text_encoder": CLIPTextModel.from_pretrained(
            root, subfolder="text_encoder", dtype=dtype, local_files_only=True
        ),
        "tokenizer": CLIPTokenizer.from_pretrained(root, subfolder="tokenizer", local_files_only=True),
        "unet": UNet2DConditionModel.from_pretrained(root, subfolder="unet", torch_dtype=dtype, local_files_only=True),
        "scheduler": _animatediff_scheduler(DDIMScheduler.load_config(root, subfolder="scheduler")),
    }


def _load_model(model_class, weights: DiffusionWeights, source: ModelWeights, dtype: torch.dtype):
    """A MotionAdapter or ControlNetModel from its diffusers folder or its single file plus local config."""
    if source.single_file is not None:
        return model_class.from_single_file(
            str(_resolve(weights.folder, source.single_file)),
            config=str(_resolve(weights.folder, source.single_file_config)),
            local_files_only=True,
            torch_dtype=dtype,
        )
    return model_class.from_pretrained(
        str(_resolve(weights.folder, source.subfolder)), torch_dtype=dtype, local_files_only=True
    )


def load_components(
    weights: DiffusionWeights, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32
) -> DiffusionComponents:
    """Load the seven components from local files only, in `dtype` on `device`, in evaluation mode.

    Raises MissingWeightsError (message from `missing_weights_message`) before loading anything when a model is
    missing. The hub is switched offline for the process first.
    """
    # 1. Refuse before loading anything.
    missing = check_weights(weights)
    if missing:
        raise MissingWeightsError(missing_weights_message(missing))
    # 2. Load offline.
    _hub_offline()
    loaded = _load_stable_diffusion(weights, dtype)
    loaded["motion_adapter"] = _load_model(MotionAdapter, weights, weights.motion_adapter, dtype)
    loaded["controlnet"] = _load_model(ControlNetModel, weights, weights.controlnet_depth, dtype)
    # 3. Place on the device, inference mode.
    for name, module in loaded.items():
        if isinstance(module, torch.nn.Module):
            loaded[name] = module.to(device).eval()
    return DiffusionComponents(**loaded)


_DTYPES = {"float32": torch.float32, "float16": torch.float16, "bfloat16": torch.bfloat16}
_loaded: dict[str, DiffusionComponents] = {}


def load_components_cached(
    weights: DiffusionWeights, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32
) -> DiffusionComponents:
    """`load_components`, remembered for the process: the same weights (by `weights_identity`), device and dtype
    return the same objects. Only the latest set is kept (SD-1.5 + adapter + ControlNet are ~7 GB in float32)."""
    key = json.dumps([weights_identity(weights), str(device), str(dtype)], sort_keys=True)
    if key not in _loaded:
        _loaded.clear()
        _loaded[key] = load_components(weights, device, dtype)
    return _loaded[key]


def diffusion_weights(generation: Mapping[str, Any]) -> DiffusionWeights:
    """`DiffusionWeights` from the `generation` config group: `weights` (the folder), `stable_diffusion`,
    `motion_adapter`, `controlnet_depth` (subfolder names) and, when present, `<model>_single_file` and
    `<model>_single_file_config`."""
    if not generation.get("weights"):
        raise ValueError("generation.weights is empty; set it to the folder holding the diffusion models")

    def model(key: str) -> ModelWeights:
        return ModelWeights(
            generation.get(key, key.replace("_", "-")),
            generation.get(f"{key}_single_file"),
            generation.get(f"{key}_single_file_config"),
        )

    return DiffusionWeights(
        folder=str(generation["weights"]),
        stable_diffusion=model("stable_diffusion"),
        motion_adapter=model("motion_adapter"),
        controlnet_depth=model("controlnet_depth"),
    )


def auto_device_dtype(
    prefer_bfloat16: bool = False, device: str = "auto", dtype: str = "auto"
) -> tuple[torch.device, torch.dtype]:
    """Device and dtype of the components.

    "auto" device: CUDA when present, else CPU. "auto" dtype: float16 on CUDA (bfloat16 when `prefer_bfloat16`
    and the GPU supports it), float32 on CPU (the pipelines run the whole model in the components' dtype; the
    notes' CPU bfloat16 figures used autocast). Explicit "cpu"/"cuda" and "float32"/"float16"/"bfloat16" win.
    """
    if device not in ("auto", "cpu", "cuda") or dtype not in ("auto", *_DTYPES):
        raise ValueError(f"device must be auto|cpu|cuda and dtype auto|{'|'.join(_DTYPES)}, got {device}, {dtype}")
    if device == "cuda" and not torch.cuda.is_available():
        raise ValueError("generation.device=cuda but torch sees no CUDA device; use device=auto or cpu")
    chosen = torch.device("cuda" if device == "cuda" or (device == "auto" and torch.cuda.is_available()) else "cpu")
    if dtype != "auto":
        return chosen, _DTYPES[dtype]
    if chosen.type == "cuda":
        bfloat16 = prefer_bfloat16 and torch.cuda.is_bf16_supported()
        return chosen, torch.bfloat16 if bfloat16 else torch.float16
    return chosen, torch.float32
