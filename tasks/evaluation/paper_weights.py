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
    source: str
    folder: bool = False

    def reason(self, path: str | None) -> str | None:
        """The report's "not computed" line when the file is not at ``path`` (None when it is there)."""
        if not path:
            return (f"not computed: weights not present ({self.key} is not set; download {self.file} from "
                    f"{self.source} and run with {self.key}=/path/to/{self.file})")
        if self.folder and not (Path(path).expanduser() / "config.json").is_file():
            return (f"not computed: weights not present (no folder with a config.json at {path}, named by "
                    f"{self.key}; download the {self.file} folder from {self.source} to that path)")
        if not self.folder and not Path(path).expanduser().is_file():
            return (f"not computed: weights not present (no file at {path}, named by {self.key}; download "
                    f"{self.file} from {self.source} to that path)")
        return None


PAPER_WEIGHTS: tuple[PaperWeights, ...] = (
    PaperWeights("imaging_quality_musiq", "VBench imaging quality (MUSIQ, SPAQ)", "paper_metrics.musiq_weights",
                 "musiq_spaq_ckpt-358bb6af.pth",
                 "https://github.com/chaofengc/IQA-PyTorch/releases/download/v0.1-weights/musiq_spaq_ckpt-358bb6af.pth"),
    PaperWeights("motion_smoothness_amt", "VBench motion smoothness (AMT-S)", "paper_metrics.amt_weights", "amt-s.pth",
                 "https://huggingface.co/lalala125/AMT/resolve/main/amt-s.pth"),
    PaperWeights("physical_commonsense", "Physical commonsense [0, 1]: VideoPhy-2 autorater, share of videos rated >= 4",
                 "paper_metrics.videophy_weights", "videophy_2_auto",
                 "https://huggingface.co/videophysics/videophy_2_auto", folder=True),
    PaperWeights("physical_commonsense_videocon",
                 "Physical commonsense [0, 1]: VideoCon-Physics, P(Yes) / (P(Yes) + P(No))",
                 "paper_metrics.videocon_weights", "videocon_physics",
                 "https://huggingface.co/videophysics/videocon_physics", folder=True),
)
# a second value of the VideoPhy-2 rater's weights (same run): its mean 1-5 rating, on VideoPhy-2's own scale
RATING_COLUMN = ("physical_commonsense_rating", "VideoPhy-2 autorater mean rating (1-5)")

# a folder's files up to this size are digested by content; larger (weight shards) by name, size and mtime
_CONTENT_DIGEST_BYTES = 64 << 20


def _path(cfg: Mapping[str, Any], spec: PaperWeights) -> str | None:
    return cfg.get(spec.key.split(".", 1)[1])


def absent_reason(cfg: Mapping[str, Any], spec: PaperWeights) -> str | None:
    """``spec``'s "not computed" line for the ``paper_metrics`` group ``cfg`` (None when its file is there)."""
    return spec.reason(_path(cfg, spec))


def present_weights(cfg: Mapping[str, Any]) -> dict[str, Path]:
    """metric -> checkpoint file, for the weights of the ``paper_metrics`` group ``cfg`` that are present."""
    return {s.metric: Path(_path(cfg, s)).expanduser() for s in PAPER_WEIGHTS if s.reason(_path(cfg, s)) is None}


def _identity(path: Path) -> str:
    """sha256 of a checkpoint file; of a folder: of its files' names with their sha256 (small files) or size and
    mtime (weight shards above 64 MiB, so that a 14 GB folder is not re-read on every run)."""
    import hashlib

    from tasks.core.params import file_sha256

    if path.is_file():
        return file_sha256(path)
    parts = []
    for f in sorted(p for p in path.rglob("*") if p.is_file()):
        st = f.stat()
        parts.append(f"{f.relative_to(path)}:" + (file_sha256(f) if st.st_size <= _CONTENT_DIGEST_BYTES
                                                  else f"{st.st_size}:{st.st_mtime_ns}"))
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()


def weights_identity(cfg: Mapping[str, Any]) -> dict[str, str]:
    """metric -> digest of the present checkpoints (the pre-flight check records it in the cache key)."""
    return {metric: _identity(path) for metric, path in present_weights(cfg).items()}
