"""Which downloaded weights the paper's own video metrics need, where to get them, and the report's line when they
are absent (paper sec. 4.1, Table 1).  Nothing here downloads anything.

* VBench imaging quality: MUSIQ with SPAQ weights, the file ``musiq_spaq_ckpt-358bb6af.pth`` (IQA-PyTorch's
  release, the file VBench itself fetches), named by ``paper_metrics.musiq_weights``;
* VBench motion smoothness: AMT-S, the file ``amt-s.pth`` (the AMT authors' release, VBench's ``amt_model``), named
  by ``paper_metrics.amt_weights``;
* VideoPhy-2 physical commonsense: the release folder ``videophy_2_auto`` (``config.json``, weights, tokenizer
  files; mPLUG-Owl-Video 7B, about 14 GB in bfloat16, :mod:`tasks.evaluation.videophy`), named by
  ``paper_metrics.videophy_weights``;
* VideoCon-Physics physical commonsense (VideoPhy's P(Yes) / (P(Yes) + P(No)) scorer, the same architecture): the
  release folder ``videocon_physics``, named by ``paper_metrics.videocon_weights``.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tasks.core.hub import HubSource

__all__ = ["PAPER_WEIGHTS", "PaperWeights", "absent_reason", "present_weights",
           "weights_identity"]


@dataclass(frozen=True)
class PaperWeights:
    """One downloadable checkpoint: the metric it enables, its config key, file (or folder) name and where to get
    it.  A folder checkpoint is present when its ``config.json`` is."""

    metric: str
    heading: str  # Table 1 column
    key: str  # config path naming the local file or folder
    file: str
    source: str  # where the authors publish it
    hub: HubSource  # the Hugging Face repository (and file) `hf download` fetches
    folder: bool = False

    def command(self, path: str | Path) -> str:
        """The ``hf download`` command that puts this checkpoint at ``path`` (a file's name must be ``file``: the
        command keeps the repository's file name)."""
        path = Path(path)
        return self.hub.command(path if self.folder else path.parent)

    def reason(self, path: str | None) -> str | None:
        """The report's "not computed" line when the file is not at ``path`` (None when it is there)."""
        if not path:
            return (f"not computed: weights not present ({self.key} is not set; fetch {self.file} with "
                    f"`{self.command(Path('/path/to') / self.file)}` and run with {self.key}=/path/to/{self.file})")
        rename = "" if self.folder or Path(path).name == self.file else f", then rename {self.file} to {Path(path).name}"
        fetch = f"fetch it with `{self.command(path if self.folder else Path(path).parent / self.file)}`{rename}"
        if self.folder and not (Path(path).expanduser() / "config.json").is_file():
            return (f"not computed: weights not present (no folder with a config.json at {path}, named by "
                    f"{self.key}; {fetch})")
        if not self.folder and not Path(path).expanduser().is_file():
            return f"not computed: weights not present (no file at {path}, named by {self.key}; {fetch})"
        return None


PAPER_WEIGHTS: tuple[PaperWeights, ...] = (
    PaperWeights("imaging_quality_musiq", "VBench imaging quality (MUSIQ, SPAQ)", "paper_metrics.musiq_weights",
                 "musiq_spaq_ckpt-358bb6af.pth",
                 "https://github.com/chaofengc/IQA-PyTorch/releases/download/v0.1-weights/musiq_spaq_ckpt-358bb6af.pth",
                 HubSource("chaofengc/IQA-PyTorch-Weights", files=("musiq_spaq_ckpt-358bb6af.pth",))),
    PaperWeights("motion_smoothness_amt", "VBench motion smoothness (AMT-S)", "paper_metrics.amt_weights", "amt-s.pth",
                 "https://huggingface.co/lalala125/AMT/resolve/main/amt-s.pth",
                 HubSource("lalala125/AMT", files=("amt-s.pth",))),
    PaperWeights("physical_commonsense", "Physical commonsense [0, 1]: VideoPhy-2 autorater, share of videos rated >= 4",
                 "paper_metrics.videophy_weights", "videophy_2_auto",
                 "https://huggingface.co/videophysics/videophy_2_auto", HubSource("videophysics/videophy_2_auto"),
                 folder=True),
    PaperWeights("physical_commonsense_videocon",
                 "Physical commonsense [0, 1]: VideoCon-Physics, P(Yes) / (P(Yes) + P(No))",
                 "paper_metrics.videocon_weights", "videocon_physics",
                 "https://huggingface.co/videophysics/videocon_physics", HubSource("videophysics/videocon_physics"),
                 folder=True),
)
# a second value of the VideoPhy-2 rater's weights (same run): its mean 1-5 rating, on VideoPhy-2's own scale
RATING_COLUMN = ("physical_commonsense_rating", "VideoPhy-2 autorater mean rating (1-5)")


def _path(cfg: Mapping[str, Any], spec: PaperWeights) -> str | None:
    return cfg.get(spec.key.split(".", 1)[1])


def absent_reason(cfg: Mapping[str, Any], spec: PaperWeights) -> str | None:
    """``spec``'s "not computed" line for the ``paper_metrics`` group ``cfg`` (None when its file is there)."""
    return spec.reason(_path(cfg, spec))


def present_weights(cfg: Mapping[str, Any]) -> dict[str, Path]:
    """metric -> checkpoint file, for the weights of the ``paper_metrics`` group ``cfg`` that are present."""
    return {s.metric: Path(_path(cfg, s)).expanduser() for s in PAPER_WEIGHTS if s.reason(_path(cfg, s)) is None}


def _identity(path: Path) -> str:
    """sha256 of a checkpoint file; of a folder: of its files' names with their sha256.  Digests are remembered
    across runs by (path, size, mtime) (:mod:`tasks.core.digest_cache`), so a 14 GB folder is read once per
    version, not on every run, and the key still follows the content."""
    import hashlib

    from tasks.core.digest_cache import file_digest

    if path.is_file():
        return file_digest(path)
    parts = [f"{f.relative_to(path)}:{file_digest(f)}" for f in sorted(p for p in path.rglob("*") if p.is_file()
                                                                        and ".cache" not in p.parts)]
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()


def weights_identity(cfg: Mapping[str, Any]) -> dict[str, str]:
    """metric -> digest of the present checkpoints (the pre-flight check records it in the cache key)."""
    return {metric: _identity(path) for metric, path in present_weights(cfg).items()}
