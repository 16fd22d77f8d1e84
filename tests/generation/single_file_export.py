"""Original-format ("single file") checkpoints of the tiny test components, for testing ``from_single_file`` loading.

Users hold SD-1.5 fine-tunes as one LDM-layout ``.safetensors`` (``model.diffusion_model.*``, ``first_stage_model.*``,
``cond_stage_model.transformer.*``) and AnimateDiff motion modules as the original ``mm_sd_v15_v2.ckpt`` layout
(``...motion_modules.N.temporal_transformer...attention_blocks.0...``).  Here the tiny diffusers components are
written in those layouts by inverting diffusers' own conversion (diffusers' ``scripts/
convert_diffusers_to_original_stable_diffusion.py`` mapping, generalised to any block count and layers per block), so
that loading them back exercises diffusers' real LDM -> diffusers conversion.  The round trip is checked by the
tests (every tensor equal after loading).
"""
from __future__ import annotations

from pathlib import Path

import torch
from safetensors.torch import save_file

from tasks.generation.components import DiffusionComponents

_RESNET = [("in_layers.0", "norm1"), ("in_layers.2", "conv1"), ("out_layers.0", "norm2"), ("out_layers.3", "conv2"),
           ("emb_layers.1", "time_emb_proj"), ("skip_connection", "conv_shortcut")]
_VAE_RESNET = [("nin_shortcut", "conv_shortcut"), ("norm_out", "conv_norm_out")]
_VAE_ATTENTION = [("norm.", "group_norm."), ("q.", "to_q."), ("k.", "to_k."), ("v.", "to_v."),
                  ("proj_out.", "to_out.0.")]


def _unet_map(unet) -> dict[str, str]:
    """diffusers UNet2DConditionModel key prefix -> LDM prefix (``model.diffusion_model.`` added by the caller)."""
    cfg = unet.config
    n, layers = len(cfg.block_out_channels), cfg.layers_per_block
    m = {"time_embedding.linear_1.": "time_embed.0.", "time_embedding.linear_2.": "time_embed.2.",
         "conv_in.": "input_blocks.0.0.", "conv_norm_out.": "out.0.", "conv_out.": "out.2.",
         "mid_block.attentions.0.": "middle_block.1."}
    for j in range(2):
        m[f"mid_block.resnets.{j}."] = f"middle_block.{2 * j}."
    for i in range(n):
        for j in range(layers):
            m[f"down_blocks.{i}.resnets.{j}."] = f"input_blocks.{(layers + 1) * i + j + 1}.0."
            m[f"down_blocks.{i}.attentions.{j}."] = f"input_blocks.{(layers + 1) * i + j + 1}.1."
        m[f"down_blocks.{i}.downsamplers.0.conv."] = f"input_blocks.{(layers + 1) * (i + 1)}.0.op."
        up_has_attention = "CrossAttn" in cfg.up_block_types[i]
        for j in range(layers + 1):
            m[f"up_blocks.{i}.resnets.{j}."] = f"output_blocks.{(layers + 1) * i + j}.0."
            m[f"up_blocks.{i}.attentions.{j}."] = f"output_blocks.{(layers + 1) * i + j}.1."
        m[f"up_blocks.{i}.upsamplers.0."] = f"output_blocks.{(layers + 1) * i + layers}.{2 if up_has_attention else 1}."
    return m


def _rename(key: str, prefixes: dict[str, str], inner: list[tuple[str, str]]) -> str:
    for diffusers_prefix, ldm_prefix in sorted(prefixes.items(), key=lambda kv: -len(kv[0])):
        if key.startswith(diffusers_prefix):
            rest = key[len(diffusers_prefix):]
            if "resnets" in diffusers_prefix or diffusers_prefix.startswith("mid_block.resnets"):
                for ldm, diffusers in inner:
                    rest = rest.replace(diffusers, ldm)
            return ldm_prefix + rest
    raise KeyError(f"no LDM name for {key}")


def ldm_unet_state(unet) -> dict[str, torch.Tensor]:
    prefixes = _unet_map(unet)
    return {"model.diffusion_model." + _rename(k, prefixes, _RESNET): v for k, v in unet.state_dict().items()}


def ldm_vae_state(vae) -> dict[str, torch.Tensor]:
    n = len(vae.config.block_out_channels)
    layers = vae.config.layers_per_block
    prefixes = {"encoder.conv_norm_out.": "encoder.norm_out.", "decoder.conv_norm_out.": "decoder.norm_out.",
                "encoder.mid_block.attentions.0.": "encoder.mid.attn_1.",
                "decoder.mid_block.attentions.0.": "decoder.mid.attn_1."}
    for part in ("encoder", "decoder"):
        for j in range(2):
            prefixes[f"{part}.mid_block.resnets.{j}."] = f"{part}.mid.block_{j + 1}."
    for i in range(n):
        for j in range(layers):
            prefixes[f"encoder.down_blocks.{i}.resnets.{j}."] = f"encoder.down.{i}.block.{j}."
        prefixes[f"encoder.down_blocks.{i}.downsamplers.0."] = f"encoder.down.{i}.downsample."
        for j in range(layers + 1):
            prefixes[f"decoder.up_blocks.{i}.resnets.{j}."] = f"decoder.up.{n - 1 - i}.block.{j}."
        prefixes[f"decoder.up_blocks.{i}.upsamplers.0."] = f"decoder.up.{n - 1 - i}.upsample."
    out = {}
    for key, value in vae.state_dict().items():
        if ".mid_block.attentions.0." in key:
            name = _rename(key, prefixes, [])
            for ldm, diffusers in _VAE_ATTENTION:
                name = name.replace("attn_1." + diffusers, "attn_1." + ldm)
            if value.ndim == 2:  # linear -> 1 x 1 convolution, as the original VAE stores them
                value = value[:, :, None, None]
            out["first_stage_model." + name] = value
            continue
        name = _rename(key, prefixes, _VAE_RESNET) if any(key.startswith(p) for p in prefixes) else key
        out["first_stage_model." + name] = value
    return out


def save_ldm_stable_diffusion(components: DiffusionComponents, path: Path) -> None:
    """The SD base (UNet, VAE, CLIP text encoder) as one LDM-layout safetensors file."""
    state = ldm_unet_state(components.unet) | ldm_vae_state(components.vae)
    # the original CLIP layout keeps transformers' ``text_model.`` level (transformers >= 5.6 flattened it away)
    state |= {"cond_stage_model.transformer.text_model." + k.removeprefix("text_model."): v
              for k, v in components.text_encoder.state_dict().items()}
    save_file({k: v.contiguous().clone() for k, v in state.items()}, str(path))


def save_original_motion_module(components: DiffusionComponents, path: Path) -> None:
    """The motion adapter in the original AnimateDiff layout (``temporal_transformer``, ``attention_blocks``,
    ``norms``, ``ff_norm``, with the sinusoidal ``pos_encoder.pe`` buffers diffusers drops)."""
    out = {}
    for key, value in components.motion_adapter.state_dict().items():
        head, sep, rest = key.partition("motion_modules.")
        index, _, tail = rest.partition(".")
        tail = (tail.replace("attn1", "attention_blocks.0").replace("attn2", "attention_blocks.1")
                .replace("norm1", "norms.0").replace("norm2", "norms.1").replace("norm3", "ff_norm"))
        out[f"{head}{sep}{index}.temporal_transformer.{tail}"] = value
        if tail.endswith("attention_blocks.0.to_q.weight"):
            pe = f"{head}{sep}{index}.temporal_transformer.{tail.removesuffix('to_q.weight')}pos_encoder.pe"
            out[pe] = torch.zeros(1, components.motion_adapter.config.motion_max_seq_length, value.shape[1])
    save_file({k: v.contiguous().clone() for k, v in out.items()}, str(path))


def save_original_controlnet(components: DiffusionComponents, path: Path) -> None:
    """The ControlNet in the original layout of lllyasviel's ``control_*.pth`` files (``control_model.``: the UNet's
    encoder half under its LDM names, ``input_hint_block``, ``zero_convs``, ``middle_block_out``)."""
    controlnet = components.controlnet
    prefixes = {k: v for k, v in _unet_map(components.unet).items() if not k.startswith(("up_blocks", "conv_norm_out",
                                                                                           "conv_out"))}
    blocks = len(controlnet.controlnet_cond_embedding.blocks)
    prefixes |= {"controlnet_cond_embedding.conv_in.": "input_hint_block.0.",
                 # diffusers' converter reads conv_out at index 14 whatever the block count (SD-1.5's 6 blocks)
                 "controlnet_cond_embedding.conv_out.": "input_hint_block.14.",
                 "controlnet_mid_block.": "middle_block_out.0."}
    prefixes |= {f"controlnet_cond_embedding.blocks.{i}.": f"input_hint_block.{2 * (i + 1)}." for i in range(blocks)}
    prefixes |= {f"controlnet_down_blocks.{i}.": f"zero_convs.{i}.0." for i in range(len(controlnet.controlnet_down_blocks))}
    state = {"control_model." + _rename(k, prefixes, _RESNET): v for k, v in controlnet.state_dict().items()}
    save_file({k: v.contiguous().clone() for k, v in state.items()}, str(path))
