"""The declared ``transformers`` floor matches the keywords we call it with: ``from_pretrained(dtype=...)`` (used to
load the text encoder, components.py) exists from transformers 4.56; the installed version meets the floor and the
keyword takes effect (a model saved in float32 loads in bfloat16).  The weights extra declares what real weights
need."""
from __future__ import annotations

import tomllib
from importlib.metadata import version
from pathlib import Path

import torch
from packaging.requirements import Requirement
from packaging.version import Version
from transformers import CLIPTextConfig, CLIPTextModel

PYPROJECT = tomllib.loads((Path(__file__).resolve().parents[2] / "pyproject.toml").read_text())
DTYPE_KEYWORD_SINCE = Version("4.56")


def _requirement(name: str, group: list[str]) -> Requirement:
    return next(r for r in map(Requirement, group) if r.name == name)


def test_transformers_floor_is_the_release_with_the_dtype_keyword_and_it_takes_effect(tmp_path):
    transformers = _requirement("transformers", PYPROJECT["project"]["dependencies"])
    floors = [Version(s.version) for s in transformers.specifier if s.operator == ">="]
    assert floors and min(floors) >= DTYPE_KEYWORD_SINCE
    assert Version(version("transformers")) in transformers.specifier
    CLIPTextModel(CLIPTextConfig(hidden_size=8, intermediate_size=16, num_attention_heads=2, num_hidden_layers=1,
                                 vocab_size=50)).save_pretrained(tmp_path)
    loaded = CLIPTextModel.from_pretrained(tmp_path, dtype=torch.bfloat16, local_files_only=True)
    assert {p.dtype for p in loaded.parameters()} == {torch.bfloat16}


def test_the_weights_extra_declares_low_memory_loading_and_the_videophy_tokenizer():
    extra = {Requirement(r).name for r in PYPROJECT["project"]["optional-dependencies"]["weights"]}
    assert {"accelerate", "sentencepiece", "protobuf"} <= extra
    assert not {"accelerate", "sentencepiece"} & {Requirement(r).name for r in PYPROJECT["project"]["dependencies"]}
