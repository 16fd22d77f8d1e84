"""AMT-S frame interpolation (Li et al., "AMT: All-Pairs Multi-Field Transforms for Efficient Frame Interpolation",
CVPR 2023) as VBench's motion-smoothness interpolator (Huang et al., CVPR 2024), paper sec. 4.1 Table 1.

Our own torch implementation of the published AMT-S network, with parameter names equal to those of the released
checkpoint (``amt-s.pth``: ``{"state_dict": ...}``), so that ``load_state_dict(strict=True)`` of it works:

* a RAFT-style feature encoder at 1/8 resolution (7 x 7 stride-2 convolution, instance norm, three pairs of bottleneck
  blocks with 32, 64 and 96 channels, 1 x 1 projection to 84) whose features of both frames give a bidirectional
  all-pairs correlation volume (dot products / sqrt(84)) pooled into 4 levels, looked up in a 7 x 7 window (radius 3);
* a context pyramid (four stride-2 levels, 20/32/44/56 channels, PReLU) per frame;
* coarse-to-fine decoders (IFRNet-style, residual blocks whose last 20 channels take a side path) predicting the
  flows from the intermediate frame t to both inputs and an intermediate feature, each refined once by an update
  block from the correlation looked up at the flows scaled to the input frames (linear motion: F_0->1 = F_t->1 / t);
* the last decoder predicts 3 flow pairs, occlusion masks and residuals at full resolution; the 3 candidate frames
  (warped inputs blended by the mask, plus the input mean and the residual) are averaged and corrected by a small
  convolution block; the result is clipped to [0, 1].

VBench's recipe: frames in RGB / 255, replicate-padded (centred) to multiples of 16, t = 1/2, scale factor 1 (no
resizing on CPU); predictions unpadded and converted back to uint8 by truncation (x 255, clipped to [0, 255]).
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["AMT", "AmtConfig", "amt_midpoint", "load_amt"]

_PAD_DIVISOR = 16


@dataclass(frozen=True)
class AmtConfig:
    """Architecture sizes; the defaults are the published AMT-S."""

    channels: tuple[int, ...] = (20, 32, 44, 56)
    skip_channels: int = 20
    encoder_widths: tuple[int, ...] = (32, 64, 96)
    feature_dim: int = 84
    hidden_dim: int = 76
    flow_dim: int = 20
    corr_dim: int = 64
    fc_dim: int = 68
    num_flows: int = 3
    corr_levels: int = 4
    corr_radius: int = 3

    @classmethod
    def from_state_dict(cls, state: Mapping[str, torch.Tensor]) -> AmtConfig:
        """The sizes a checkpoint was saved with (correlation levels and radius: the published 4 and 3)."""
        return cls(channels=tuple(state[f"encoder.pyramid{i}.0.0.weight"].shape[0] for i in range(1, 5)),
                   skip_channels=state["decoder4.convblock.1.conv2.0.weight"].shape[0],
                   encoder_widths=(state["feat_encoder.conv1.weight"].shape[0],
                                   state["feat_encoder.layer2.0.conv3.weight"].shape[0],
                                   state["feat_encoder.layer3.0.conv3.weight"].shape[0]),
                   feature_dim=state["feat_encoder.conv2.weight"].shape[0],
                   hidden_dim=state["update4.gru.0.weight"].shape[0],
                   flow_dim=state["update4.convf2.weight"].shape[0], corr_dim=state["update4.convc1.weight"].shape[0],
                   fc_dim=state["update4.conv.weight"].shape[0], num_flows=state["comb_block.0.weight"].shape[1] // 3)


def _resize(x: torch.Tensor, factor: float) -> torch.Tensor:
    return F.interpolate(x, scale_factor=factor, mode="bilinear", align_corners=False)


def _warp(image: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
    """Backward warp image(x + flow(x)), bilinear, border replicated; flow (batch, 2 = (x, y), y, x) in pixels."""
    b, _, h, w = flow.shape
    xs = torch.linspace(-1.0, 1.0, w).view(1, 1, w).expand(b, h, w)
    ys = torch.linspace(-1.0, 1.0, h).view(1, h, 1).expand(b, h, w)
    grid = torch.stack([xs + flow[:, 0] / ((w - 1.0) / 2.0), ys + flow[:, 1] / ((h - 1.0) / 2.0)], dim=-1)
    return F.grid_sample(image, grid.to(image), mode="bilinear", padding_mode="border", align_corners=True)


def _convrelu(cin: int, cout: int, kernel: int = 3, stride: int = 1, padding: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, kernel, stride, padding), nn.PReLU(cout))


class BottleneckBlock(nn.Module):
    """RAFT bottleneck with instance norm (no parameters); a strided block has a 1 x 1 projection shortcut."""

    def __init__(self, cin: int, planes: int, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, planes // 4, 1)
        self.conv2 = nn.Conv2d(planes // 4, planes // 4, 3, padding=1, stride=stride)
        self.conv3 = nn.Conv2d(planes // 4, planes, 1)
        self.downsample = (nn.Sequential(nn.Conv2d(cin, planes, 1, stride=stride), nn.InstanceNorm2d(planes))
                           if stride != 1 else None)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(F.instance_norm(self.conv1(x)))
        y = F.relu(F.instance_norm(self.conv2(y)))
        y = F.relu(F.instance_norm(self.conv3(y)))
        return F.relu((self.downsample(x) if self.downsample is not None else x) + y)


class SmallEncoder(nn.Module):
    def __init__(self, c: AmtConfig):
        super().__init__()
        w1, w2, w3 = c.encoder_widths
        self.conv1 = nn.Conv2d(3, w1, 7, stride=2, padding=3)
        self.layer1 = nn.Sequential(BottleneckBlock(w1, w1), BottleneckBlock(w1, w1))
        self.layer2 = nn.Sequential(BottleneckBlock(w1, w2, 2), BottleneckBlock(w2, w2))
        self.layer3 = nn.Sequential(BottleneckBlock(w2, w3, 2), BottleneckBlock(w3, w3))
        self.conv2 = nn.Conv2d(w3, c.feature_dim, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.relu(F.instance_norm(self.conv1(x)))
        return self.conv2(self.layer3(self.layer2(self.layer1(x))))


class ResBlock(nn.Module):
    """IFRNet residual block: the last ``side`` channels pass through an extra convolution after each stage."""

    def __init__(self, channels: int, side: int):
        super().__init__()
        self.side = side
        self.conv1 = _convrelu(channels, channels)
        self.conv2 = _convrelu(side, side)
        self.conv3 = _convrelu(channels, channels)
        self.conv4 = _convrelu(side, side)
        self.conv5 = nn.Conv2d(channels, channels, 3, 1, 1)
        self.prelu = nn.PReLU(channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.conv1(x)
        out = self.conv3(torch.cat([out[:, :-self.side], self.conv2(out[:, -self.side:])], 1))
        out = self.conv5(torch.cat([out[:, :-self.side], self.conv4(out[:, -self.side:])], 1))
        return self.prelu(x + out)


class Encoder(nn.Module):
    def __init__(self, channels: tuple[int, ...]):
        super().__init__()
        prev = 3
        for i, ch in enumerate(channels, 1):
            self.register_module(f"pyramid{i}", nn.Sequential(_convrelu(prev, ch, 3, 2, 1), _convrelu(ch, ch)))
            prev = ch
        self.levels = len(channels)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        out = []
        for i in range(1, self.levels + 1):
            x = getattr(self, f"pyramid{i}")(x)
            out.append(x)
        return out


class InitDecoder(nn.Module):
    def __init__(self, cin: int, cout: int, skip: int):
        super().__init__()
        self.convblock = nn.Sequential(_convrelu(2 * cin + 1, 2 * cin), ResBlock(2 * cin, skip),
                                       nn.ConvTranspose2d(2 * cin, cout + 4, 4, 2, 1))

    def forward(self, f0: torch.Tensor, f1: torch.Tensor, embt: torch.Tensor) -> tuple[torch.Tensor, ...]:
        out = self.convblock(torch.cat([f0, f1, embt.expand(len(f0), 1, *f0.shape[2:])], 1))
        return out[:, 0:2], out[:, 2:4], out[:, 4:]


class IntermediateDecoder(nn.Module):
    def __init__(self, cin: int, cout: int, skip: int):
        super().__init__()
        self.convblock = nn.Sequential(_convrelu(3 * cin + 4, 3 * cin), ResBlock(3 * cin, skip),
                                       nn.ConvTranspose2d(3 * cin, cout + 4, 4, 2, 1))

    def forward(self, ft, f0, f1, flow0, flow1) -> tuple[torch.Tensor, ...]:
        out = self.convblock(torch.cat([ft, _warp(f0, flow0), _warp(f1, flow1), flow0, flow1], 1))
        return (out[:, 0:2] + 2.0 * _resize(flow0, 2.0), out[:, 2:4] + 2.0 * _resize(flow1, 2.0), out[:, 4:])


class MultiFlowDecoder(nn.Module):
    def __init__(self, cin: int, skip: int, num_flows: int):
        super().__init__()
        self.num_flows = num_flows
        self.convblock = nn.Sequential(_convrelu(3 * cin + 4, 3 * cin), ResBlock(3 * cin, skip),
                                       nn.ConvTranspose2d(3 * cin, 8 * num_flows, 4, 2, 1))

    def forward(self, ft, f0, f1, flow0, flow1) -> tuple[torch.Tensor, ...]:
        n = self.num_flows
        out = self.convblock(torch.cat([ft, _warp(f0, flow0), _warp(f1, flow1), flow0, flow1], 1))
        delta0, delta1, mask, residual = torch.split(out, [2 * n, 2 * n, n, 3 * n], 1)
        return (delta0 + 2.0 * _resize(flow0, 2.0).repeat(1, n, 1, 1),
                delta1 + 2.0 * _resize(flow1, 2.0).repeat(1, n, 1, 1), torch.sigmoid(mask), residual)


class SmallUpdateBlock(nn.Module):
    """One residual update of the flows and the intermediate feature from the looked-up correlation; a block of a
    finer level works at 1/8 resolution and upsamples its updates by ``scale``."""

    def __init__(self, c: AmtConfig, cdim: int, scale: int | None = None):
        super().__init__()
        planes = c.corr_levels * (2 * c.corr_radius + 1) ** 2
        self.scale = scale
        self.convc1 = nn.Conv2d(2 * planes, c.corr_dim, 1)
        self.convf1 = nn.Conv2d(4, 2 * c.flow_dim, 7, padding=3)
        self.convf2 = nn.Conv2d(2 * c.flow_dim, c.flow_dim, 3, padding=1)
        self.conv = nn.Conv2d(c.corr_dim + c.flow_dim, c.fc_dim, 3, padding=1)

        def pair(cin: int, cout: int) -> nn.Sequential:
            return nn.Sequential(nn.Conv2d(cin, c.hidden_dim, 3, padding=1), nn.LeakyReLU(0.1),
                                 nn.Conv2d(c.hidden_dim, cout, 3, padding=1))

        self.gru = pair(c.fc_dim + 4 + cdim, c.hidden_dim)
        self.feat_head = pair(c.hidden_dim, cdim)
        self.flow_head = pair(c.hidden_dim, 4)

    def forward(self, feature, flow, corr) -> tuple[torch.Tensor, torch.Tensor]:
        lrelu = nn.functional.leaky_relu
        if self.scale is not None:
            feature = _resize(feature, 1.0 / self.scale)
        motion = torch.cat([lrelu(self.convc1(corr), 0.1), lrelu(self.convf2(lrelu(self.convf1(flow), 0.1)), 0.1)], 1)
        out = self.gru(torch.cat([lrelu(self.conv(motion), 0.1), flow, feature], 1))
        delta_feature, delta_flow = self.feat_head(out), self.flow_head(out)
        if self.scale is not None:
            delta_feature = _resize(delta_feature, self.scale)
            delta_flow = self.scale * _resize(delta_flow, self.scale)
        return delta_feature, delta_flow


@dataclass
class _BidirCorrelation:
    """All-pairs correlation of two (1, C, h, w) feature maps, both ways, pooled into ``levels`` levels; looked up
    bilinearly (zeros outside) in a (2r+1)^2 window around given (x, y) pixel positions of the 1/8 grid."""

    fmap0: torch.Tensor
    fmap1: torch.Tensor
    levels: int
    radius: int
    pyramid: list[torch.Tensor] = field(init=False)
    pyramid_t: list[torch.Tensor] = field(init=False)

    def __post_init__(self):
        b, dim, h, w = self.fmap0.shape
        corr = (self.fmap0.reshape(b, dim, h * w).transpose(1, 2) @ self.fmap1.reshape(b, dim, h * w)) / dim ** 0.5
        corr = corr.reshape(b, h, w, 1, h, w)
        self.pyramid = [corr.reshape(b * h * w, 1, h, w)]
        self.pyramid_t = [corr.permute(0, 4, 5, 3, 1, 2).reshape(b * h * w, 1, h, w)]
        for _ in range(self.levels - 1):
            self.pyramid.append(F.avg_pool2d(self.pyramid[-1], 2, stride=2))
            self.pyramid_t.append(F.avg_pool2d(self.pyramid_t[-1], 2, stride=2))

    def lookup(self, coords0: torch.Tensor, coords1: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        r = self.radius
        b, _, h, w = coords0.shape
        line = torch.linspace(-r, r, 2 * r + 1)
        # window offsets: the first window axis moves x, the second y (as in the released model)
        offsets = torch.stack(torch.meshgrid(line, line, indexing="ij"), dim=-1).view(1, 2 * r + 1, 2 * r + 1, 2)

        def sample(volumes: list[torch.Tensor], coords: torch.Tensor) -> torch.Tensor:
            centres = coords.permute(0, 2, 3, 1).reshape(b * h * w, 1, 1, 2)
            out = []
            for i, volume in enumerate(volumes):
                pos = centres / 2 ** i + offsets
                vh, vw = volume.shape[-2:]
                grid = torch.stack([2 * pos[..., 0] / (vw - 1) - 1, 2 * pos[..., 1] / (vh - 1) - 1], dim=-1)
                out.append(F.grid_sample(volume, grid, align_corners=True).view(b, h, w, -1))
            return torch.cat(out, dim=-1).permute(0, 3, 1, 2).contiguous()

        return sample(self.pyramid, coords0), sample(self.pyramid_t, coords1)


class AMT(nn.Module):
    """The AMT-S network; ``forward(img0, img1, embt)`` takes (1, 3, y, x) RGB in [0, 1] with y, x multiples of 16 and
    the time (1, 1, 1, 1) in (0, 1); returns the predicted frame at that time, (1, 3, y, x) in [0, 1]."""

    def __init__(self, config: AmtConfig = AmtConfig()):
        super().__init__()
        c = self.config = config
        ch, skip = c.channels, c.skip_channels
        self.feat_encoder = SmallEncoder(c)
        self.encoder = Encoder(ch)
        self.decoder4 = InitDecoder(ch[3], ch[2], skip)
        self.decoder3 = IntermediateDecoder(ch[2], ch[1], skip)
        self.decoder2 = IntermediateDecoder(ch[1], ch[0], skip)
        self.decoder1 = MultiFlowDecoder(ch[0], skip, c.num_flows)
        self.update4 = SmallUpdateBlock(c, ch[2])
        self.update3 = SmallUpdateBlock(c, ch[1], 2)
        self.update2 = SmallUpdateBlock(c, ch[0], 4)
        self.comb_block = nn.Sequential(nn.Conv2d(3 * c.num_flows, 6 * c.num_flows, 3, 1, 1),
                                        nn.PReLU(6 * c.num_flows), nn.Conv2d(6 * c.num_flows, 3, 3, 1, 1))

    def forward(self, img0: torch.Tensor, img1: torch.Tensor, embt: torch.Tensor) -> torch.Tensor:
        mean = torch.cat([img0, img1], 2).mean(dim=(1, 2, 3), keepdim=True)
        img0, img1 = img0 - mean, img1 - mean
        b, _, h, w = img0.shape
        ys, xs = torch.meshgrid(torch.arange(h // 8), torch.arange(w // 8), indexing="ij")
        coord = torch.stack([xs, ys]).float()[None].expand(b, -1, -1, -1)
        fmap0, fmap1 = self.feat_encoder(torch.cat([img0, img1], 0)).split(b, dim=0)
        corr = _BidirCorrelation(fmap0, fmap1, self.config.corr_levels, self.config.corr_radius)
        f0, f1 = self.encoder(img0), self.encoder(img1)

        def refine(update, ft, flow0, flow1, downsample):
            # linear motion: the flow t -> 1 scaled by 1/t reaches frame 1 from frame 0, and t -> 0 by 1/(1-t)
            f0s = flow0 if downsample == 1 else _resize(flow0, 1.0 / downsample) / downsample
            f1s = flow1 if downsample == 1 else _resize(flow1, 1.0 / downsample) / downsample
            c0, c1 = corr.lookup(coord + f1s / embt, coord + f0s / (1.0 - embt))
            delta_ft, delta_flow = update(ft, torch.cat([f0s, f1s], 1), torch.cat([c0, c1], 1))
            return ft + delta_ft, flow0 + delta_flow[:, 0:2], flow1 + delta_flow[:, 2:4]

        flow0, flow1, ft = self.decoder4(f0[3], f1[3], embt)
        ft, flow0, flow1 = refine(self.update4, ft, flow0, flow1, 1)
        flow0, flow1, ft = self.decoder3(ft, f0[2], f1[2], flow0, flow1)
        ft, flow0, flow1 = refine(self.update3, ft, flow0, flow1, 2)
        flow0, flow1, ft = self.decoder2(ft, f0[1], f1[1], flow0, flow1)
        ft, flow0, flow1 = refine(self.update2, ft, flow0, flow1, 4)
        flow0, flow1, mask, residual = self.decoder1(ft, f0[0], f1[0], flow0, flow1)
        # the candidate frames of the flow pairs, averaged and corrected
        n = self.config.num_flows
        warped0 = _warp(img0.repeat_interleave(n, 0), flow0.reshape(b * n, 2, h, w))
        warped1 = _warp(img1.repeat_interleave(n, 0), flow1.reshape(b * n, 2, h, w))
        mask = mask.reshape(b * n, 1, h, w)
        candidates = (mask * warped0 + (1 - mask) * warped1 + mean.repeat_interleave(n, 0)
                      + residual.reshape(b * n, 3, h, w)).reshape(b, n, 3, h, w)
        out = candidates.mean(1) + self.comb_block(candidates.reshape(b, 3 * n, h, w))
        return out.clamp(0.0, 1.0)


def load_amt(path: str | Path) -> AMT:
    """AMT from a checkpoint file in the released format (``{"state_dict": ...}``), sizes read from its shapes, loaded
    with ``strict=True``, in eval mode."""
    state = torch.load(Path(path).expanduser(), map_location="cpu", weights_only=True)["state_dict"]
    net = AMT(AmtConfig.from_state_dict(state))
    net.load_state_dict(state, strict=True)
    return net.eval()


def amt_midpoint(net: AMT, frame0: np.ndarray, frame1: np.ndarray) -> np.ndarray:
    """VBench's AMT prediction of the frame halfway between two (y, x, 3) uint8 RGB frames: RGB / 255, centred
    replicate padding to multiples of 16, t = 1/2, unpadded, x 255 clipped and truncated to uint8."""
    h, w = frame0.shape[:2]
    pad_y, pad_x = -h % _PAD_DIVISOR, -w % _PAD_DIVISOR
    pads = (pad_x // 2, pad_x - pad_x // 2, pad_y // 2, pad_y - pad_y // 2)

    device = next(net.parameters()).device

    def tensor(frame: np.ndarray) -> torch.Tensor:
        x = torch.from_numpy(np.ascontiguousarray(frame)).permute(2, 0, 1)[None].float().to(device) / 255.0
        return F.pad(x, pads, mode="replicate")

    with torch.inference_mode():
        out = net(tensor(frame0), tensor(frame1), torch.full((1, 1, 1, 1), 0.5, device=device))
    out = out[0, :, pads[2]:pads[2] + h, pads[0]:pads[0] + w].cpu()
    return (out * 255.0).permute(1, 2, 0).numpy().clip(0, 255).astype(np.uint8)
