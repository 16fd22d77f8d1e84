"""A tiny mPLUG-Owl-Video rater saved as a release folder (config.json, model.safetensors, tokenizer files), shared by
the VideoPhy-2 and VideoCon-Physics tests: a word-level tokenizer over the prompts' words and a 2-layer network whose
every parameter is drawn N(0, 0.5) (the zero-initialised queries, eos and positions too)."""
from __future__ import annotations

import json
import re
from pathlib import Path

import torch

from tasks.evaluation.videophy import MplugOwlVideo, OwlConfig

QUERIES = 4
SPECIAL = ["<unk>", "<s>", "</s>"]


def word_tokenizer(text: str, extra: set[str] = frozenset()):
    """A word-level fast tokenizer over the words and punctuation of ``text`` (the video placeholder removed), the
    digits 0-5 and ``extra``, after the special tokens <unk>, <s>, </s>."""
    from tokenizers import Tokenizer, decoders, models, pre_tokenizers
    from transformers import PreTrainedTokenizerFast

    words = sorted(set(re.findall(r"\w+|[^\w\s]", text.replace("<|video|>", ""))) | set("012345") | set(extra))
    tok = Tokenizer(models.WordLevel({w: i for i, w in enumerate(SPECIAL + words)}, unk_token="<unk>"))
    tok.pre_tokenizer = pre_tokenizers.Whitespace()
    tok.decoder = decoders.WordPiece()
    return PreTrainedTokenizerFast(tokenizer_object=tok, unk_token="<unk>", bos_token="<s>", eos_token="</s>",
                                   pad_token="<unk>")


def rater_config(vocab: int) -> dict:
    """The release's config.json at a tiny size (hidden 32, 2 layers, 28 px images of 14 px patches)."""
    return {"model_type": "mplug-owl", "num_query_tokens": QUERIES,
            "vision_config": {"hidden_size": 32, "intermediate_size": 64, "num_hidden_layers": 2,
                              "num_attention_heads": 2, "image_size": 28, "patch_size": 14, "layer_norm_eps": 1e-6},
            "visual_abstractor_config": {"hidden_size": 32, "intermediate_size": 64, "num_hidden_layers": 2,
                                         "num_attention_heads": 2, "encoder_hidden_size": 32, "layer_norm_eps": 1e-6},
            "text_config": {"model_type": "llama", "vocab_size": vocab, "hidden_size": 32, "intermediate_size": 64,
                            "num_hidden_layers": 2, "num_attention_heads": 2, "num_key_value_heads": 2,
                            "max_position_embeddings": 256, "bos_token_id": 1, "eos_token_id": 2,
                            "pad_token_id": 0}}


def save_rater(folder: Path, tok, seed: int = 0) -> MplugOwlVideo:
    """Write a tiny rater with tokenizer ``tok`` into the new folder ``folder``; returns the network saved."""
    from safetensors.torch import save_file

    cfg = rater_config(len(tok))
    torch.manual_seed(seed)
    net = MplugOwlVideo(OwlConfig.from_json(cfg))
    for p in net.parameters():  # the zero-initialised queries, eos and positions too
        torch.nn.init.normal_(p, std=0.5)
    folder.mkdir()
    (folder / "config.json").write_text(json.dumps(cfg))
    save_file({k: v.contiguous().clone() for k, v in net.state_dict().items()}, folder / "model.safetensors")
    tok.save_pretrained(folder)
    return net
