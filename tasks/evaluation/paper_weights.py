"""Which downloaded weights the paper's own video metrics need, where to get them, and the report's line when they
are absent (paper sec. 4.1, Table 1).  Nothing here downloads anything.

* VBench imaging quality: MUSIQ with SPAQ weights, the file ``musiq_spaq_ckpt-358bb6af.pth`` (IQA-PyTorch's
  release, the file VBench itself fetches), named by ``paper_metrics.musiq_weights``;
* VBench motion smoothness: AMT-S, the file ``amt-s.pth`` (the AMT authors' release, VBench's ``amt_model``), named
  by ``paper_metrics.amt_weights``;
* VideoPhy-2 physical commonsense (VideoCon-Physics): never computed here, :data:`PHYSICAL_COMMONSENSE_REASON`.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["PAPER_WEIGHTS", "PHYSICAL_COMMONSENSE_REASON", "PaperWeights", "absent_reason", "present_weights",
           "weights_identity"]


@dataclass(frozen=True)
class PaperWeights:
    """One downloadable checkpoint: the metric it enables, its config key, file name and where to get it."""

    metric: str
    heading: str  # Table 1 column
    key: str  # config path naming the local file
    file: str
    source: str

    def reason(self, path: str | None) -> str | None:
        """The report's "not computed" line when the file is not at ``path`` (None when it is there)."""
        if not path:
            return (f"not computed: weights not present ({self.key} is not set; download {self.file} from "
                    f"{self.source} and run with {self.key}=/path/to/{self.file})")
        if not Path(path).expanduser().is_file():
            return (f"not computed: weights not present (no file at {path}, named by {self.key}; download "
                    f"{self.file} from {self.source} to that path)")
        return None


PAPER_WEIGHTS: tuple[PaperWeights, ...] = (
    PaperWeights("imaging_quality_musiq", "VBench imaging quality (MUSIQ, SPAQ)", "paper_metrics.musiq_weights",
                 "musiq_spaq_ckpt-358bb6af.pth",
                 "https://github.com/chaofengc/IQA-PyTorch/releases/download/v0.1-weights/musiq_spaq_ckpt-358bb6af.pth"),
    PaperWeights("motion_smoothness_amt", "VBench motion smoothness (AMT-S)", "paper_metrics.amt_weights", "amt-s.pth",
                 "https://huggingface.co/lalala125/AMT/resolve/main/amt-s.pth"),
)

PHYSICAL_COMMONSENSE_REASON = (
    "not computed: weights not present, and not loadable here with them: VideoPhy-2's physical-commonsense rater "
    "(huggingface.co/videophysics/videophy2_autoeval, trained from VideoPhy-1's VideoCon-Physics, "
    "videophysics/videocon_physics; 7B parameters, about 14 GB in bfloat16) is "
    "mPLUG-Owl-Video 7B (LLaMA-7B + ViT-L/14 + visual abstractor), loaded by the custom mplug_owl_video code of "
    "github.com/Hritikbansal/videophy; transformers 5.24 has no mPLUG-Owl architecture and no registry package "
    "ships one")


def _path(cfg: Mapping[str, Any], spec: PaperWeights) -> str | None:
    return cfg.get(spec.key.split(".", 1)[1])


def absent_reason(cfg: Mapping[str, Any], spec: PaperWeights) -> str | None:
    """``spec``'s "not computed" line for the ``paper_metrics`` group ``cfg`` (None when its file is there)."""
    return spec.reason(_path(cfg, spec))


def present_weights(cfg: Mapping[str, Any]) -> dict[str, Path]:
    """metric -> checkpoint file, for the weights of the ``paper_metrics`` group ``cfg`` that are present."""
    return {s.metric: Path(_path(cfg, s)).expanduser() for s in PAPER_WEIGHTS if s.reason(_path(cfg, s)) is None}


def weights_identity(cfg: Mapping[str, Any]) -> dict[str, str]:
    """metric -> sha256 of the present checkpoint files (the pre-flight check records it in the cache key)."""
    from tasks.core.params import file_sha256

    return {metric: file_sha256(path) for metric, path in present_weights(cfg).items()}
