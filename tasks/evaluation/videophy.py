"""VideoPhy-2 physical commonsense (Bansal et al., "VideoPhy-2", 2025; the paper's sec. 4.1 Table 1): the
``videophy_2_autoeval`` rater, an mPLUG-Owl-Video model (Ye et al., "mPLUG-Owl", 2023; LLaMA-7B + ViT-L/14 video
encoder + visual abstractor) fine-tuned from VideoCon-Physics.

Our own torch implementation of mPLUG-Owl-Video, with module and parameter names equal to those of the public
``MplugOwlForConditionalGeneration`` (github.com/X-PLUG/mPLUG-Owl ``mplug_owl_video/modeling_mplug_owl.py``, the code
github.com/Hritikbansal/videophy loads), so that ``load_state_dict(strict=True)`` of a release folder works; the
language model is transformers' ``LlamaForCausalLM`` (attribute ``language_model``):

* vision encoder (``vision_model``): 14 px patches (convolution without bias), class token, learned positions,
  pre-layer-norm; per layer, when there is more than one frame, a local temporal module added to the tokens (layer
  norm of the patch tokens, 1 x 1 x 1 convolution to half width, depthwise 3 x 1 x 1 convolution over time, QuickGELU,
  1 x 1 x 1 convolution back; its class-token output is the input class token), then pre-norm self-attention (one
  fused ``query_key_value``, laid out per head as (q, k, v)) and a QuickGELU MLP, per frame; a final layer norm;
* visual abstractor (``abstractor``): ``num_query_tokens`` learned queries and as many temporal queries attend, in
  each layer, to themselves and to all frames' tokens (queries and frame tokens layer-normed separately); the output
  is the normed query plus a projection, plus a SwiGLU MLP with an inner layer norm; the query outputs are projected to
  the language width (``visual_fc`` + ``temporal_visual_fc`` of the temporal outputs) and followed by ``vit_eos``;
* the prompt's ``<|video|>`` stands for ``num_query_tokens + 1`` positions, replaced by those embeddings.

VideoPhy-2's scoring recipe (``VIDEOPHY2/inference.py``, ``template.py``): 32 frames at the centres of equal segments
of the video, resized to 224 x 224, CLIP-normalised; the physical-commonsense prompt (:data:`PROMPT_PHYSICS`) with a
BOS token; greedy decoding; the answer is parsed for the first of "zero".."five", "0".."5" it contains (else 0), the
1-5 rating (5 = full compliance with physical laws); on the paper's [0, 1] scale the share of videos rated >= 4
(:func:`share_rated_at_least`).  VideoCon-Physics (the same architecture, VideoPhy's release
huggingface.co/videophysics/videocon_physics) answers Yes / No to :data:`PROMPT_VIDEOCON`; its score is
P(Yes) / (P(Yes) + P(No)) of the next token (:meth:`VideoPhyRater.p_yes`), in [0, 1].  The release (huggingface.co/videophysics/videophy_2_auto:
``config.json``, ``pytorch_model-0000?-of-00002.bin`` in bfloat16, ``tokenizer.model``) is run in bfloat16 like
VideoPhy-2's inference, except the layer norms, which compute in float32 with float32 weights and return the input's
dtype (mPLUG-Owl's ``LayerNormFp32``), on ``paper_metrics.device`` (CUDA when present).  Remaining difference: the
reference decodes and resizes the MP4 with decord (FFmpeg's scaler); here the final frames are resized by torch
(bicubic), before any MP4 encoding.
"""
from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["CLIP_MEAN", "CLIP_STD", "MplugOwlVideo", "OwlConfig", "PROMPT_PHYSICS", "PROMPT_VIDEOCON", "VideoPhyRater",
           "frame_indices", "keep_layer_norms_fp32", "load_videophy", "parse_rating", "share_rated_at_least",
           "video_pixels"]

PROMPT_PHYSICS = (
    "The following is a conversation between a curious human and an AI assistant. "
    "The assistant gives helpful, detailed, and polite answers to the user's questions.\n"
    "Human: <|video|>\n"
    "Human: Does this video adhere to the physical laws? "
    "Rate the video on a scale from 1 to 5, where 5 means full compliance and 1 means significant violations.\n"
    "AI: ")
# VideoCon-Physics' physical-commonsense prompt (videophy ``entailment_inference.py`` inputs: the VideoPhy physics
# question, answered Yes / No; note "human and AI assistant", without "an")
PROMPT_VIDEOCON = (
    "The following is a conversation between a curious human and AI assistant. "
    "The assistant gives helpful, detailed, and polite answers to the user's questions.\n"
    "Human: <|video|>\n"
    "Human: Does this video follow the physical laws?\n"
    "AI: ")
VIDEO_TOKEN = "<|video|>"
CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
CLIP_STD = (0.26862954, 0.26130258, 0.27577711)
# the answer words VideoPhy-2's parser looks for, in its order
_RATINGS = {"zero": 0, "one": 1, "two": 2, "three": 3, "four": 4, "five": 5,
            "0": 0, "1": 1, "2": 2, "3": 3, "4": 4, "5": 5}


@dataclass(frozen=True)
class OwlConfig:
    """mPLUG-Owl-Video sizes (the ``vision_config`` / ``visual_abstractor_config`` / ``num_query_tokens`` of a release's
    ``config.json``; the language model's sizes are its ``text_config``)."""

    vision: dict[str, Any]
    abstractor: dict[str, Any]
    text: dict[str, Any]
    num_query_tokens: int = 64

    @classmethod
    def from_json(cls, cfg: dict[str, Any]) -> OwlConfig:
        vision = {"hidden_size": 1024, "intermediate_size": 4096, "num_hidden_layers": 24, "num_attention_heads": 16,
                  "image_size": 224, "patch_size": 14, "layer_norm_eps": 1e-6, **cfg.get("vision_config", {})}
        abstractor = {"hidden_size": 1024, "intermediate_size": 4096, "num_hidden_layers": 6,
                      "num_attention_heads": 16, "encoder_hidden_size": 1024, "layer_norm_eps": 1e-6,
                      **cfg.get("visual_abstractor_config", {})}
        return cls(vision, abstractor, dict(cfg["text_config"]), int(cfg.get("num_query_tokens", 64)))


class _QuickGELU(nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * torch.sigmoid(1.702 * x)


class _Embeddings(nn.Module):
    def __init__(self, c: dict[str, Any]):
        super().__init__()
        d, p = c["hidden_size"], c["patch_size"]
        self.cls_token = nn.Parameter(torch.zeros(1, 1, d))
        self.patch_embed = nn.Conv2d(3, d, p, stride=p, bias=False)
        self.position_embedding = nn.Parameter(torch.zeros(1, (c["image_size"] // p) ** 2 + 1, d))
        self.pre_layernorm = nn.LayerNorm(d, eps=c["layer_norm_eps"])

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        """(b, 3, t, h, w) -> (b, t, 1 + patches, d)."""
        b, _, t = pixels.shape[:3]
        x = self.patch_embed(pixels.transpose(1, 2).flatten(0, 1)).flatten(2).transpose(1, 2)
        x = torch.cat([self.cls_token.expand(b * t, 1, -1), x], dim=1)
        x = self.pre_layernorm(x + self.position_embedding[:, :x.shape[1]])
        return x.unflatten(0, (b, t))


class _LocalTemporal(nn.Module):
    def __init__(self, c: dict[str, Any]):
        super().__init__()
        d = c["hidden_size"]
        self.side = c["image_size"] // c["patch_size"]
        self.ln = nn.LayerNorm(d)
        self.down_proj = nn.Conv3d(d, d // 2, 1)
        self.conv = nn.Conv3d(d // 2, d // 2, (3, 1, 1), padding=(1, 0, 0), groups=d // 2)
        self.up_proj = nn.Conv3d(d // 2, d, 1)
        self.act = _QuickGELU()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(b, t, 1 + h w, d) -> the same shape; the class token is passed through."""
        cls, patches = x[:, :, :1], self.ln(x[:, :, 1:])
        b, t, n, d = patches.shape
        y = patches.permute(0, 3, 1, 2).reshape(b, d, t, self.side, self.side)
        y = self.up_proj(self.act(self.conv(self.down_proj(y))))
        return torch.cat([cls, y.flatten(3).permute(0, 2, 3, 1)], dim=2)


class _VisionAttention(nn.Module):
    def __init__(self, c: dict[str, Any]):
        super().__init__()
        d = c["hidden_size"]
        self.heads = c["num_attention_heads"]
        self.query_key_value = nn.Linear(d, 3 * d)
        self.dense = nn.Linear(d, d)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, s, d = x.shape
        qkv = self.query_key_value(x).reshape(b, s, self.heads, 3, d // self.heads).permute(3, 0, 2, 1, 4)
        out = F.scaled_dot_product_attention(qkv[0], qkv[1], qkv[2])
        return self.dense(out.transpose(1, 2).reshape(b, s, d))


class _VisionMLP(nn.Module):
    def __init__(self, c: dict[str, Any]):
        super().__init__()
        self.fc1 = nn.Linear(c["hidden_size"], c["intermediate_size"])
        self.fc2 = nn.Linear(c["intermediate_size"], c["hidden_size"])
        self.act = _QuickGELU()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(self.act(self.fc1(x)))


class _VisionLayer(nn.Module):
    def __init__(self, c: dict[str, Any]):
        super().__init__()
        self.temporal = _LocalTemporal(c)
        self.self_attn = _VisionAttention(c)
        self.input_layernorm = nn.LayerNorm(c["hidden_size"], eps=c["layer_norm_eps"])
        self.mlp = _VisionMLP(c)
        self.post_attention_layernorm = nn.LayerNorm(c["hidden_size"], eps=c["layer_norm_eps"])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, t = x.shape[:2]
        if t > 1:
            x = x + self.temporal(x)
        x = x.flatten(0, 1)
        x = x + self.self_attn(self.input_layernorm(x))
        x = x + self.mlp(self.post_attention_layernorm(x))
        return x.unflatten(0, (b, t))


class _VisionEncoder(nn.Module):
    def __init__(self, c: dict[str, Any]):
        super().__init__()
        self.layers = nn.ModuleList(_VisionLayer(c) for _ in range(c["num_hidden_layers"]))


class _VisionModel(nn.Module):
    def __init__(self, c: dict[str, Any]):
        super().__init__()
        self.embeddings = _Embeddings(c)
        self.encoder = _VisionEncoder(c)
        self.post_layernorm = nn.LayerNorm(c["hidden_size"], eps=c["layer_norm_eps"])

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        """(b, 3, t, h, w) CLIP-normalised -> (b, t, 1 + patches, d)."""
        x = self.embeddings(pixels)
        for layer in self.encoder.layers:
            x = layer(x)
        return self.post_layernorm(x)


class _CrossAttention(nn.Module):
    def __init__(self, c: dict[str, Any]):
        super().__init__()
        d = c["hidden_size"]
        self.heads = c["num_attention_heads"]
        self.query = nn.Linear(d, d)
        self.key = nn.Linear(c["encoder_hidden_size"], d)
        self.value = nn.Linear(c["encoder_hidden_size"], d)

    def forward(self, q: torch.Tensor, kv: torch.Tensor) -> torch.Tensor:
        def heads(x: torch.Tensor) -> torch.Tensor:
            return x.unflatten(-1, (self.heads, -1)).transpose(1, 2)

        out = F.scaled_dot_product_attention(heads(self.query(q)), heads(self.key(kv)), heads(self.value(kv)))
        return out.transpose(1, 2).flatten(2)


class _AbstractorMLP(nn.Module):
    def __init__(self, c: dict[str, Any]):
        super().__init__()
        inner = c["intermediate_size"]
        if inner != 2816:  # the released code's SwiGLU width: 2/3 of intermediate_size, rounded up to 256
            inner = 256 * -(-int(2 * inner / 3) // 256)
        self.w1 = nn.Linear(c["hidden_size"], inner)
        self.w2 = nn.Linear(inner, c["hidden_size"])
        self.w3 = nn.Linear(c["hidden_size"], inner)
        self.ffn_ln = nn.LayerNorm(inner, eps=c["layer_norm_eps"])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.w2(self.ffn_ln(F.silu(self.w1(x)) * self.w3(x)))


class _CrossOutput(nn.Module):
    def __init__(self, c: dict[str, Any]):
        super().__init__()
        self.out_proj = nn.Linear(c["hidden_size"], c["hidden_size"])
        self.norm2 = nn.LayerNorm(c["hidden_size"])
        self.mlp = _AbstractorMLP(c)

    def forward(self, context: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        x = x + self.out_proj(context)
        return x + self.mlp(self.norm2(x))


class _CrossAttentionBlock(nn.Module):
    def __init__(self, c: dict[str, Any]):
        super().__init__()
        self.attention = _CrossAttention(c)
        self.output = _CrossOutput(c)
        self.norm1 = nn.LayerNorm(c["hidden_size"])
        self.normk = nn.LayerNorm(c["hidden_size"])

    def forward(self, queries: torch.Tensor, frames: torch.Tensor) -> torch.Tensor:
        q = self.norm1(queries)
        return self.output(self.attention(q, torch.cat([q, self.normk(frames)], dim=1)), q)


class _AbstractorLayer(nn.Module):
    def __init__(self, c: dict[str, Any]):
        super().__init__()
        self.crossattention = _CrossAttentionBlock(c)


class _AbstractorEncoder(nn.Module):
    def __init__(self, c: dict[str, Any]):
        super().__init__()
        self.layers = nn.ModuleList(_AbstractorLayer(c) for _ in range(c["num_hidden_layers"]))


class _Abstractor(nn.Module):
    def __init__(self, c: dict[str, Any], language_width: int):
        super().__init__()
        self.encoder = _AbstractorEncoder(c)
        self.visual_fc = nn.Linear(c["hidden_size"], language_width)
        self.temporal_visual_fc = nn.Linear(c["hidden_size"], language_width)
        self.vit_eos = nn.Parameter(torch.zeros(1, 1, language_width))

    def forward(self, queries: torch.Tensor, temporal_queries: torch.Tensor, frames: torch.Tensor) -> torch.Tensor:
        """queries, temporal_queries: (b, q, d); frames: (b, t, n, d) -> (b, q + 1, language width)."""
        n = queries.shape[1]
        x = torch.cat([queries, temporal_queries], dim=1) if frames.shape[1] > 1 else queries
        frames = frames.flatten(1, 2)
        for layer in self.encoder.layers:
            x = layer.crossattention(x, frames)
        out = self.visual_fc(x[:, :n])
        if x.shape[1] > n:
            out = out + self.temporal_visual_fc(x[:, n:])
        return torch.cat([out, self.vit_eos.expand(out.shape[0], 1, -1)], dim=1)


class MplugOwlVideo(nn.Module):
    """mPLUG-Owl-Video with the released ``MplugOwlForConditionalGeneration``'s parameter names."""

    def __init__(self, cfg: OwlConfig):
        from transformers import LlamaConfig, LlamaForCausalLM

        super().__init__()
        self.cfg = cfg
        width = cfg.abstractor["hidden_size"]
        self.vision_model = _VisionModel(cfg.vision)
        self.query_tokens = nn.Parameter(torch.zeros(1, cfg.num_query_tokens, width))
        self.temporal_query_tokens = nn.Parameter(torch.zeros(1, cfg.num_query_tokens, width))
        self.abstractor = _Abstractor(cfg.abstractor, cfg.text["hidden_size"])
        text = {k: v for k, v in cfg.text.items() if k not in ("architectures", "model_type", "_name_or_path")}
        self.language_model = LlamaForCausalLM(LlamaConfig(**text))

    def video_embeddings(self, pixels: torch.Tensor) -> torch.Tensor:
        """(b, 3, t, h, w) CLIP-normalised frames -> (b, num_query_tokens + 1, language width)."""
        frames = self.vision_model(pixels)
        b = frames.shape[0]
        return self.abstractor(self.query_tokens.expand(b, -1, -1), self.temporal_query_tokens.expand(b, -1, -1),
                               frames)

    def prompt_embeddings(self, ids: list[int], pixels: torch.Tensor) -> torch.Tensor:
        """(1, len(ids), language width): the ids' embeddings, the run of negative ids (the video's positions)
        replaced by :meth:`video_embeddings`."""
        table = self.language_model.get_input_embeddings()
        tokens = torch.tensor([ids], device=table.weight.device)
        embeds = table(tokens.clamp(min=0))
        start = ids.index(next(i for i in ids if i < 0))
        video = self.video_embeddings(pixels)
        return torch.cat([embeds[:, :start], video, embeds[:, start + video.shape[1]:]], dim=1)


class LayerNormFp32(nn.LayerNorm):
    """LayerNorm computed in float32 (weights kept float32), output in the input's dtype, as mPLUG-Owl's."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.layer_norm(x.float(), self.normalized_shape, self.weight.float(), self.bias.float(),
                            self.eps).to(x.dtype)


def keep_layer_norms_fp32(net: nn.Module) -> None:
    """Every ``nn.LayerNorm`` of ``net`` becomes a :class:`LayerNormFp32` with float32 weights (names unchanged)."""
    for module in net.modules():
        if type(module) is nn.LayerNorm:
            module.__class__ = LayerNormFp32
            module.float()


def frame_indices(total: int, count: int) -> np.ndarray:
    """VideoPhy-2's frame choice: the centres of ``count`` equal segments of ``total`` frames (its ``get_index``)."""
    seg = (total - 1) / count
    return np.array([int(seg / 2) + int(np.round(seg * i)) for i in range(count)])


def video_pixels(video: np.ndarray, frames: int, size: int) -> torch.Tensor:
    """(frame, y, x, 3) uint8 RGB -> (1, 3, frames, size, size): sampled frames, resized, CLIP-normalised."""
    x = torch.from_numpy(np.ascontiguousarray(video[frame_indices(len(video), frames)])).permute(0, 3, 1, 2).float()
    x = F.interpolate(x, size=(size, size), mode="bicubic", align_corners=False).clamp(0, 255) / 255.0
    x = (x - torch.tensor(CLIP_MEAN)[:, None, None]) / torch.tensor(CLIP_STD)[:, None, None]
    return x.permute(1, 0, 2, 3)[None]


def share_rated_at_least(ratings: list[int] | np.ndarray, threshold: int = 4) -> float:
    """The share (in [0, 1]) of videos rated >= ``threshold`` (VideoPhy-2 reports physical commonsense as the share of
    videos its autorater scores >= 4 of 5); NaN without ratings."""
    r = np.asarray(ratings)
    return float((r >= threshold).mean()) if r.size else float("nan")


def parse_rating(answer: str) -> int:
    """VideoPhy-2's parse of a generated answer: the first rating word or digit it contains, else 0."""
    text = answer.lower().strip()
    for word, value in _RATINGS.items():
        if word in text:
            return value
    digits = "".join(c for c in text if c.isdigit())
    return int(digits) if digits and int(digits) in _RATINGS.values() else 0


@dataclass
class VideoPhyRater:
    """A loaded VideoPhy-2 rater: the network and its tokenizer.  max_new_tokens: VideoPhy-2's ``max_length`` of 256,
    which counts the generated tokens only when generation starts from embeddings."""

    net: MplugOwlVideo
    tokenizer: Any
    frames: int = 32
    max_new_tokens: int = 256

    def prompt_ids(self, prompt: str = PROMPT_PHYSICS) -> list[int]:
        """BOS, the prompt's tokens, the video as ``num_query_tokens + 1`` ids of -2 (mPLUG-Owl's video marker)."""
        ids = [self.tokenizer.bos_token_id]
        for chunk in re.split(f"({re.escape(VIDEO_TOKEN)})", prompt):
            if chunk == VIDEO_TOKEN:
                ids += [-2] * (self.net.cfg.num_query_tokens + 1)
            elif chunk:
                ids += self.tokenizer(chunk, add_special_tokens=False)["input_ids"]
        return ids

    def p_yes(self, video: np.ndarray, prompt: str = PROMPT_VIDEOCON) -> float:
        """VideoCon-Physics' score of a (frame, y, x, 3) uint8 RGB video, in [0, 1]: the next-token probabilities
        after the prompt, P(Yes) / (P(Yes) + P(No)), "Yes" and "No" the first token of each word without special
        tokens (videophy ``entailment_inference.py``: ``get_entail``).  No text is generated or parsed."""
        yes = self.tokenizer.encode("Yes", add_special_tokens=False)[0]
        no = self.tokenizer.encode("No", add_special_tokens=False)[0]
        dtype, device = self.net.query_tokens.dtype, self.net.query_tokens.device
        pixels = video_pixels(video, self.frames, self.net.cfg.vision["image_size"]).to(device, dtype)
        with torch.inference_mode():
            embeds = self.net.prompt_embeddings(self.prompt_ids(prompt), pixels)
            logits = self.net.language_model(inputs_embeds=embeds).logits[0, -1].float()
        prob = torch.softmax(logits, dim=-1)
        return float(prob[yes] / (prob[yes] + prob[no]))

    def rate(self, video: np.ndarray) -> tuple[int, str]:
        """(1-5 rating, 0 when unparsable; the generated answer) of a (frame, y, x, 3) uint8 RGB video."""
        dtype, device = self.net.query_tokens.dtype, self.net.query_tokens.device
        pixels = video_pixels(video, self.frames, self.net.cfg.vision["image_size"]).to(device, dtype)
        with torch.inference_mode():
            embeds = self.net.prompt_embeddings(self.prompt_ids(), pixels)
            out = self.net.language_model.generate(
                inputs_embeds=embeds, attention_mask=torch.ones(embeds.shape[:2], dtype=torch.long, device=device),
                max_new_tokens=self.max_new_tokens, do_sample=False,
                pad_token_id=self.tokenizer.pad_token_id or 0, eos_token_id=self.tokenizer.eos_token_id)
        answer = self.tokenizer.decode(out[0].tolist(), skip_special_tokens=True)
        return parse_rating(answer), answer


def _state_dict(folder: Path) -> dict[str, torch.Tensor]:
    """All tensors of a release folder's ``*.safetensors`` (else ``pytorch_model*.bin``) files; the rotary-embedding
    frequency buffers older LLaMA code saved are dropped (recomputed by transformers)."""
    files = sorted(folder.glob("*.safetensors"))
    state: dict[str, torch.Tensor] = {}
    if files:
        from safetensors.torch import load_file

        for f in files:
            state.update(load_file(f))
    else:
        files = sorted(folder.glob("pytorch_model*.bin"))
        if not files:
            raise FileNotFoundError(f"no *.safetensors or pytorch_model*.bin weights in {folder}")
        for f in files:
            state.update(torch.load(f, map_location="cpu", weights_only=True))
    return {k: v for k, v in state.items() if not k.endswith("rotary_emb.inv_freq")}


def _tokenizer(folder: Path):
    """The folder's ``tokenizer.json`` when there is one, else its ``tokenizer.model`` read as VideoPhy-2 reads it
    (``LlamaTokenizer``; converting the sentencepiece model needs the ``sentencepiece`` package)."""
    from transformers import AutoTokenizer, LlamaTokenizer

    if (folder / "tokenizer.json").is_file():
        return AutoTokenizer.from_pretrained(folder)
    return LlamaTokenizer.from_pretrained(folder)


def load_videophy(folder: str | Path, frames: int = 32, dtype: torch.dtype = torch.bfloat16) -> VideoPhyRater:
    """The rater of a release folder (``config.json``, weights, tokenizer files), weights loaded with
    ``strict=True`` and cast to ``dtype``, in eval mode."""
    folder = Path(folder).expanduser()
    cfg = OwlConfig.from_json(json.loads((folder / "config.json").read_text()))
    net = MplugOwlVideo(cfg)
    state = _state_dict(folder)
    if "language_model.lm_head.weight" not in state and cfg.text.get("tie_word_embeddings"):
        state["language_model.lm_head.weight"] = state["language_model.model.embed_tokens.weight"]
    net.load_state_dict(state, strict=True)
    net.to(dtype)
    keep_layer_norms_fp32(net)
    return VideoPhyRater(net.eval(), _tokenizer(folder), frames=frames)
