"""The paper metrics' recipe details against their references: VBench's imaging-quality resize antialiases (as
torchvision's ``Resize``), VideoPhy-2's layer norms compute in float32 inside the bfloat16 rater, the metric networks
run on ``paper_metrics.device``, and each definition states what is scored (final frames, not decoded MP4)."""
from __future__ import annotations

import numpy as np
import torch

from tasks.evaluation.musiq import VBENCH_LONGER_SIDE_PX, vbench_resize
from tasks.evaluation.paper_metrics import DEFINITIONS
from tasks.evaluation.videophy import LayerNormFp32, keep_layer_norms_fp32


def test_vbench_resize_antialiases_one_pixel_stripes_to_grey():
    # 1-px black/white columns at 3 x the target width: bilinear without antialiasing samples every third column
    # (alternately black and white: full-contrast aliasing); with antialiasing each output averages ~3 columns
    frames = torch.from_numpy(np.tile((np.arange(1536) % 2 * 255.0)[None, None, None], (1, 3, 96, 1))).float()
    resized = vbench_resize(frames)
    assert tuple(resized.shape[-2:]) == (32, VBENCH_LONGER_SIDE_PX)
    assert resized.std(dim=-1).max() < 60  # only the residual of 3-column averages of alternating stripes
    aliased = torch.nn.functional.interpolate(frames, (32, 512), mode="bilinear", antialias=False)
    assert aliased.std(dim=-1).min() > 120
    assert torch.equal(resized, resized.round()) and torch.equal(vbench_resize(frames[..., :512]), frames[..., :512])


def test_layer_norms_compute_in_float32_inside_a_bfloat16_network():
    net = torch.nn.Sequential(torch.nn.Linear(16, 16), torch.nn.LayerNorm(16), torch.nn.Linear(16, 4))
    reference = net(torch.randn(3, 16, generator=torch.Generator().manual_seed(0)) * 50 + 300)
    net.to(torch.bfloat16)
    keep_layer_norms_fp32(net)
    norm = net[1]
    assert isinstance(norm, LayerNormFp32) and norm.weight.dtype == torch.float32
    assert set(net.state_dict()) == {"0.weight", "0.bias", "1.weight", "1.bias", "2.weight", "2.bias"}
    x = (torch.randn(3, 16, generator=torch.Generator().manual_seed(0)) * 50 + 300).to(torch.bfloat16)
    hidden = net[0](x)
    out = norm(hidden)
    assert out.dtype == torch.bfloat16
    expected = torch.nn.functional.layer_norm(hidden.float(), (16,), eps=norm.eps).to(torch.bfloat16)
    assert torch.equal(out, expected)  # weights are 1 / 0: the float32 normalisation itself, rounded once
    assert torch.allclose(net(x).float(), reference, atol=0.1)


def test_each_definition_says_the_frames_are_scored_before_mp4_encoding():
    for definition in DEFINITIONS.values():
        assert "not on frames decoded from the report's H.264 MP4" in definition
    assert "antialiasing" in DEFINITIONS["imaging_quality_musiq"]
    assert "layer norms in float32" in DEFINITIONS["physical_commonsense"] and "decord" in \
        DEFINITIONS["physical_commonsense"]
