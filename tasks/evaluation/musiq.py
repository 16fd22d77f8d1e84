"""MUSIQ (Ke et al., ICCV 2021) and VBench's imaging-quality recipe (Huang et al., CVPR 2024), paper sec. 4.1 Table 1.

Our own torch implementation of the published architecture, with parameter names equal to those of the released
PyTorch checkpoints of IQA-PyTorch (``musiq_spaq_ckpt-358bb6af.pth``, a flat state dict), so that
``load_state_dict(strict=True)`` of that file works:

* multi-scale input: the frame resized (bicubic, aspect ratio kept) so that its longer side is 224 and 384 px, plus
  the frame at its own resolution; each scale cut into 32 x 32 patches (TensorFlow "SAME" zero padding), the two
  resized scales padded (mask 0) or cut to ceil(L / 32)^2 patches; each patch carries its hashed spatial position
  (a 10 x 10 grid, nearest-neighbour hashing of the patch grid) and its scale index;
* patch stem: weight-standardised 7 x 7 stride-2 convolution (64 channels), GroupNorm, ReLU, 3 x 3 stride-2 max pool
  ("SAME"), one ResNet bottleneck (64 -> 256 channels); the 8 x 8 x 256 map (channels last) is embedded to 384;
* transformer: class token, 14 pre-norm blocks (6 heads, MLP 1152, GELU, LayerNorm eps 1e-6) with attention
  masked to the real patches, final LayerNorm, linear head on the class token (1 output: SPAQ's MOS, 0..100).

VBench's imaging quality: every frame, as uint8 RGB, is resized so that its longer side is 512 px when it is longer
(torchvision's ``transforms.Resize`` on a uint8 tensor: bilinear WITH antialiasing, the default from torchvision 0.17,
rounded back to uint8), divided by 255, scored by MUSIQ-SPAQ (inputs mapped to [-1, 1]); the video's score is the
mean over its frames divided by 100.
"""
from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["MUSIQ", "MusiqConfig", "load_musiq", "multiscale_patches", "musiq_frame_scores", "vbench_imaging_quality",
           "vbench_resize"]

VBENCH_LONGER_SIDE_PX = 512


@dataclass(frozen=True)
class MusiqConfig:
    """Architecture sizes; the defaults are the published MUSIQ.  The head has one output (the MOS), as the SPAQ
    checkpoint (IQA-PyTorch's AVA checkpoint, a 10-class distribution head, does not load)."""

    patch_size: int = 32
    token_dim: int = 64  # channels of the ResNet stem
    hidden_size: int = 384
    mlp_dim: int = 1152
    num_heads: int = 6
    num_layers: int = 14
    num_scales: int = 3
    grid_size: int = 10  # hashed spatial position grid
    longer_side_lengths: tuple[int, ...] = (224, 384)

    @classmethod
    def from_state_dict(cls, state: Mapping[str, torch.Tensor]) -> MusiqConfig:
        """The sizes a checkpoint was saved with (heads: one per 64 hidden channels, as published: 384 / 64 = 6)."""
        token_dim = state["conv_root.weight"].shape[0]
        hidden, embed_in = state["embedding.weight"].shape
        token_patch = math.isqrt(embed_in // (4 * token_dim))
        layers = {int(m.group(1)) for k in state if (m := re.match(r"transformer_encoder\.transformer\.encoderblock_"
                                                                    r"(\d+)\.", k))}
        return cls(patch_size=4 * token_patch, token_dim=token_dim, hidden_size=hidden,
                   mlp_dim=state["transformer_encoder.transformer.encoderblock_0.mlp.fc1.weight"].shape[0],
                   num_heads=max(1, hidden // 64), num_layers=len(layers),
                   num_scales=state["transformer_encoder.scaleembed_input.scale_emb"].shape[0],
                   grid_size=math.isqrt(state["transformer_encoder.posembed_input.position_emb"].shape[1]))


def _groups(channels: int) -> int:
    """GroupNorm groups: 32 as published; a stand-in narrower than 64 channels uses channels / 2."""
    return 32 if channels >= 64 else max(1, channels // 2)


def _same_pad(x: torch.Tensor, kernel: int, stride: int) -> torch.Tensor:
    """TensorFlow "SAME" zero padding of a (batch, channel, y, x) tensor for a square kernel and stride."""
    pads = []
    for size in (x.shape[-1], x.shape[-2]):
        total = max((math.ceil(size / stride) - 1) * stride + kernel - size, 0)
        pads += [total // 2, total - total // 2]
    return F.pad(x, pads)


class StdConv(nn.Conv2d):
    """Convolution with weight standardisation (per output channel: zero mean, unit std + 1e-5) and SAME padding."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        w = self.weight - self.weight.mean((1, 2, 3), keepdim=True)
        w = w / (w.std((1, 2, 3), keepdim=True) + 1e-5)
        return F.conv2d(_same_pad(x, self.kernel_size[0], self.stride[0]), w, self.bias, self.stride)


class Bottleneck(nn.Module):
    """ResNet-v2-style bottleneck of the MUSIQ stem (GroupNorm eps 1e-4, projection shortcut)."""

    def __init__(self, inplanes: int, outplanes: int):
        super().__init__()
        self.conv1 = StdConv(inplanes, inplanes, 1, bias=False)
        self.gn1 = nn.GroupNorm(_groups(inplanes), inplanes, eps=1e-4)
        self.conv2 = StdConv(inplanes, inplanes, 3, bias=False)
        self.gn2 = nn.GroupNorm(_groups(inplanes), inplanes, eps=1e-4)
        self.conv3 = StdConv(inplanes, outplanes, 1, bias=False)
        self.gn3 = nn.GroupNorm(_groups(outplanes), outplanes, eps=1e-4)
        self.conv_proj = StdConv(inplanes, outplanes, 1, bias=False)
        self.gn_proj = nn.GroupNorm(_groups(outplanes), outplanes, eps=1e-4)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        shortcut = self.gn_proj(self.conv_proj(x))
        y = F.relu(self.gn1(self.conv1(x)))
        y = F.relu(self.gn2(self.conv2(y)))
        return F.relu(self.gn3(self.conv3(y)) + shortcut)


class MultiHeadAttention(nn.Module):
    """Multi-head self-attention; pairs involving a padded patch get the logit -1000 (as the released model)."""

    def __init__(self, dim: int, num_heads: int):
        super().__init__()
        self.num_heads = num_heads
        self.query, self.key, self.value, self.out = (nn.Linear(dim, dim) for _ in range(4))

    def forward(self, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        b, n, c = x.shape

        def heads(t: torch.Tensor) -> torch.Tensor:
            return t.reshape(b, n, self.num_heads, c // self.num_heads).transpose(1, 2)

        q, k, v = heads(self.query(x)), heads(self.key(x)), heads(self.value(x))
        logits = (q @ k.transpose(-2, -1)) * (c // self.num_heads) ** -0.5
        pair = (mask[:, None, :, None] * mask[:, None, None, :]) == 0
        attn = logits.masked_fill(pair, -1e3).softmax(dim=-1)
        return self.out((attn @ v).transpose(1, 2).reshape(b, n, c))


class Mlp(nn.Module):
    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.fc1, self.fc2 = nn.Linear(dim, hidden), nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(F.gelu(self.fc1(x)))


class TransformerBlock(nn.Module):
    def __init__(self, dim: int, mlp_dim: int, num_heads: int):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=1e-6)
        self.attention = MultiHeadAttention(dim, num_heads)
        self.norm2 = nn.LayerNorm(dim, eps=1e-6)
        self.mlp = Mlp(dim, mlp_dim)

    def forward(self, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        x = x + self.attention(self.norm1(x), mask)
        return x + self.mlp(self.norm2(x))


class AddHashSpatialPositionEmbs(nn.Module):
    def __init__(self, grid_size: int, dim: int):
        super().__init__()
        self.position_emb = nn.Parameter(torch.randn(1, grid_size * grid_size, dim) * 0.02)


class AddScaleEmbs(nn.Module):
    def __init__(self, num_scales: int, dim: int):
        super().__init__()
        self.scale_emb = nn.Parameter(torch.randn(num_scales, dim) * 0.02)


class TransformerEncoder(nn.Module):
    def __init__(self, c: MusiqConfig):
        super().__init__()
        self.posembed_input = AddHashSpatialPositionEmbs(c.grid_size, c.hidden_size)
        self.scaleembed_input = AddScaleEmbs(c.num_scales, c.hidden_size)
        self.cls = nn.Parameter(torch.zeros(1, 1, c.hidden_size))
        self.encoder_norm = nn.LayerNorm(c.hidden_size, eps=1e-6)
        self.transformer = nn.ModuleDict({f"encoderblock_{i}": TransformerBlock(c.hidden_size, c.mlp_dim, c.num_heads)
                                          for i in range(c.num_layers)})

    def forward(self, x: torch.Tensor, spatial: torch.Tensor, scale: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        x = x + self.posembed_input.position_emb[0][spatial] + self.scaleembed_input.scale_emb[scale]
        x = torch.cat([self.cls.expand(len(x), -1, -1), x], dim=1)
        mask = torch.cat([torch.ones_like(mask[:, :1]), mask], dim=1)
        for block in self.transformer.values():
            x = block(x, mask)
        return self.encoder_norm(x)


def _hashed_positions(grid_size: int, count_h: int, count_w: int) -> torch.Tensor:
    """(count_h * count_w,) index into the grid_size^2 position table: each patch row / column mapped to the grid
    by nearest-neighbour resampling (row-major)."""
    grid = torch.arange(grid_size, dtype=torch.float32)[None, None]
    rows = F.interpolate(grid, size=count_h, mode="nearest")[0, 0].long()
    cols = F.interpolate(grid, size=count_w, mode="nearest")[0, 0].long()
    return (rows[:, None] * grid_size + cols[None, :]).reshape(-1)


def _scale_patches(image: torch.Tensor, c: MusiqConfig, scale_id: int, max_len: int | None
                   ) -> tuple[torch.Tensor, ...]:
    """Patches (batch, n, 3 * p * p; channel-major within a patch), spatial index, scale index and mask of one scale,
    padded (mask 0) or cut to max_len patches when given."""
    b, _, h, w = image.shape
    p = c.patch_size
    padded = _same_pad(image, p, p)
    patches = F.unfold(padded, p, stride=p).transpose(1, 2)  # (batch, n, 3 p p)
    spatial = _hashed_positions(c.grid_size, math.ceil(h / p), math.ceil(w / p)).expand(b, -1)
    mask = torch.ones(spatial.shape, dtype=image.dtype)
    if max_len is not None:
        n = patches.shape[1]
        keep = min(n, max_len)
        patches = F.pad(patches[:, :keep], (0, 0, 0, max_len - keep))
        spatial, mask = (F.pad(t[:, :keep], (0, max_len - keep)) for t in (spatial, mask))
    return patches, spatial, torch.full_like(spatial, scale_id) * mask.long(), mask


def multiscale_patches(image: torch.Tensor, c: MusiqConfig) -> tuple[torch.Tensor, ...]:
    """MUSIQ's multi-scale input of a (batch, 3, y, x) image in [-1, 1]: each resized scale (bicubic, longer side L,
    ceil(L / p)^2 patches), then the image at its own size (all its patches).  Returns patches, spatial index,
    scale index and mask, concatenated over the scales along the sequence axis."""
    h, w = image.shape[-2:]
    parts = []
    for scale_id, longer in enumerate(sorted(c.longer_side_lengths)):
        ratio = longer / max(h, w)
        resized = F.interpolate(image, (round(h * ratio), round(w * ratio)), mode="bicubic")
        parts.append(_scale_patches(resized, c, scale_id, math.ceil(longer / c.patch_size) ** 2))
    parts.append(_scale_patches(image, c, len(c.longer_side_lengths), None))
    return tuple(torch.cat(t, dim=1) for t in zip(*parts))


class MUSIQ(nn.Module):
    """The MUSIQ network; ``forward`` takes (batch, 3, y, x) RGB in [0, 1] and returns the (batch,) quality."""

    def __init__(self, config: MusiqConfig = MusiqConfig()):
        super().__init__()
        c = self.config = config
        self.conv_root = StdConv(3, c.token_dim, 7, 2, bias=False)
        self.gn_root = nn.GroupNorm(_groups(c.token_dim), c.token_dim, eps=1e-6)
        self.block1 = Bottleneck(c.token_dim, 4 * c.token_dim)
        self.embedding = nn.Linear(4 * c.token_dim * (c.patch_size // 4) ** 2, c.hidden_size)
        self.transformer_encoder = TransformerEncoder(c)
        self.head = nn.Linear(c.hidden_size, 1)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        c = self.config
        patches, spatial, scale, mask = multiscale_patches((image - 0.5) * 2.0, c)
        b, n, _ = patches.shape
        x = patches.reshape(b * n, 3, c.patch_size, c.patch_size)
        x = F.relu(self.gn_root(self.conv_root(x)))
        x = F.max_pool2d(_same_pad(x, 3, 2), 3, 2)
        x = self.block1(x).permute(0, 2, 3, 1).reshape(b, n, -1)  # channels last, as the TensorFlow original
        x = self.transformer_encoder(self.embedding(x), spatial, scale, mask)
        return self.head(x[:, 0])[:, 0]


def load_musiq(path: str | Path) -> MUSIQ:
    """MUSIQ from a checkpoint file (a flat state dict, IQA-PyTorch's release format; a ``module.`` prefix of
    data-parallel training is dropped, as IQA-PyTorch does), sizes read from its shapes, loaded with ``strict=True``,
    in eval mode."""
    state = torch.load(Path(path).expanduser(), map_location="cpu", weights_only=True)
    state = {k.removeprefix("module."): v for k, v in state.items()}
    net = MUSIQ(MusiqConfig.from_state_dict(state))
    net.load_state_dict(state, strict=True)
    return net.eval()


def vbench_resize(frames: torch.Tensor) -> torch.Tensor:
    """VBench's imaging-quality resize of (frame, 3, y, x) uint8-valued float frames: longer side down to 512 px when
    it is longer, (int(scale h), int(scale w)), bilinear with antialiasing (torchvision's Resize), rounded to 8 bits."""
    h, w = frames.shape[-2:]
    if max(h, w) <= VBENCH_LONGER_SIDE_PX:
        return frames
    scale = VBENCH_LONGER_SIDE_PX / max(h, w)
    resized = F.interpolate(frames, (int(scale * h), int(scale * w)), mode="bilinear", antialias=True)
    return resized.round().clamp(0, 255)


def musiq_frame_scores(video: np.ndarray, net: MUSIQ) -> np.ndarray:
    """MUSIQ score (the checkpoint's MOS scale, 0..100 for SPAQ) of every frame of a (frame, y, x, 3) uint8 sRGB video,
    after VBench's resize (:func:`vbench_resize`), on the network's device."""
    device = next(net.parameters()).device
    frames = vbench_resize(torch.from_numpy(np.ascontiguousarray(video)).permute(0, 3, 1, 2).float())
    with torch.inference_mode():
        return np.array([float(net(f[None].to(device) / 255.0)[0]) for f in frames])


def vbench_imaging_quality(video: np.ndarray, net: MUSIQ) -> float:
    """VBench imaging quality of one video: mean MUSIQ-SPAQ frame score / 100 (in [0, 1] for SPAQ's 0..100 MOS)."""
    return float(musiq_frame_scores(video, net).mean() / 100.0)
