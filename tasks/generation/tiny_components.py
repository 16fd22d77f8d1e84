"""Tiny randomly initialised diffusion components, built in memory offline (no hub, no files read): for the tests
and for ``python -m flows.gpu_check``.

Sizes follow diffusers' own AnimateDiff/ControlNet fast tests (block_out_channels=(8, 8), cross_attention_dim=8,
norm groups of 2): a 2-block VAE (vae_scale_factor 2), a 2-block UNet, a MotionAdapter with tiny motion blocks,
a ControlNet made by `ControlNetModel.from_unet`, a 5-layer CLIP text encoder of width 8 and a CLIPTokenizer built
in memory from a character vocabulary with `model_max_length=77`. The scheduler is DDIM with `steps_offset=1`
and `timestep_spacing="linspace"`.

The ControlNet's zero convolutions, and any other weight tensor a fresh model initialises to exactly zero (so that
it would contribute nothing), are re-drawn from a seeded normal distribution: with the published zero
initialisation the depth condition could not reach the output and the tests of conditioning would be vacuous.
"""

import string

import torch
from diffusers import AutoencoderKL, ControlNetModel, DDIMScheduler, MotionAdapter, UNet2DConditionModel
from transformers import CLIPTextConfig, CLIPTextModel, CLIPTokenizer

from tasks.generation.components import DiffusionComponents

CROSS_ATTENTION_DIM = 8
BLOCK_OUT_CHANNELS = (8, 8)
ZERO_INIT_STD = 1.0


def tiny_tokenizer() -> CLIPTokenizer:
    """CLIP BPE tokenizer over single characters (no merges), built in memory; ids 0 and 1 are the specials."""
    vocab = {"<|startoftext|>": 0, "<|endoftext|>": 1}
    for character in string.ascii_lowercase + string.digits + string.punctuation:
        vocab.setdefault(character, len(vocab))
        vocab.setdefault(character + "</w>", len(vocab))
    return CLIPTokenizer(vocab=vocab, merges=[], model_max_length=77)


def _redraw_zero_weights(model: torch.nn.Module, generator: torch.Generator) -> None:
    """Replace every all-zero weight tensor (zero convolutions, zero-initialised projections) by seeded noise."""
    with torch.no_grad():
        for name, parameter in model.named_parameters():
            if name.endswith("weight") and not parameter.any():
                parameter.copy_(torch.randn(parameter.shape, generator=generator) * ZERO_INIT_STD)


def tiny_components(seed: int = 0) -> DiffusionComponents:
    """All seven components, float32 on CPU, deterministic for a given seed."""
    torch.manual_seed(seed)
    unet = UNet2DConditionModel(
        block_out_channels=BLOCK_OUT_CHANNELS,
        layers_per_block=2,
        sample_size=8,
        in_channels=4,
        out_channels=4,
        down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"),
        up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"),
        cross_attention_dim=CROSS_ATTENTION_DIM,
        norm_num_groups=2,
    )
    vae = AutoencoderKL(
        block_out_channels=BLOCK_OUT_CHANNELS,
        in_channels=3,
        out_channels=3,
        down_block_types=("DownEncoderBlock2D", "DownEncoderBlock2D"),
        up_block_types=("UpDecoderBlock2D", "UpDecoderBlock2D"),
        latent_channels=4,
        norm_num_groups=2,
    )
    motion_adapter = MotionAdapter(
        block_out_channels=BLOCK_OUT_CHANNELS,
        motion_layers_per_block=2,
        motion_norm_num_groups=2,
        motion_num_attention_heads=4,
        motion_max_seq_length=32,
    )
    controlnet = ControlNetModel.from_unet(unet, conditioning_embedding_out_channels=(8, 8))
    text_encoder = CLIPTextModel(
        CLIPTextConfig(
            bos_token_id=0,
            eos_token_id=1,
            pad_token_id=1,
            hidden_size=CROSS_ATTENTION_DIM,
            intermediate_size=37,
            layer_norm_eps=1e-05,
            num_attention_heads=4,
            num_hidden_layers=5,
            vocab_size=1000,
        )
    )
    generator = torch.Generator().manual_seed(seed)
    for model in (unet, vae, motion_adapter, controlnet):
        _redraw_zero_weights(model, generator)
    scheduler = DDIMScheduler(
        beta_start=0.00085,
        beta_end=0.012,
        beta_schedule="linear",
        clip_sample=False,
        set_alpha_to_one=False,
        steps_offset=1,
        timestep_spacing="linspace",
    )
    return DiffusionComponents(
        vae=vae.eval(),
        text_encoder=text_encoder.eval(),
        tokenizer=tiny_tokenizer(),
        unet=unet.eval(),
        motion_adapter=motion_adapter.eval(),
        controlnet=controlnet.eval(),
        scheduler=scheduler,
    )
