"""The paper's VBench metrics where their weights are present: our MUSIQ and AMT-S networks load checkpoints in the
released formats strictly (tiny random stand-ins saved like the real files, loaded through the same loaders), the
VBench recipes run on a video, and absent weights give the report's "not computed" line naming what to fetch.

Random weights say nothing about quality: only shapes, determinism, loading, key names and the protocol arithmetic
are tested here."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tasks.core.artifacts import Array, write_artifact
from tasks.evaluation.amt import AMT, AmtConfig, amt_midpoint, load_amt
from tasks.evaluation.musiq import MUSIQ, MusiqConfig, load_musiq, musiq_frame_scores
from tasks.evaluation.paper_metrics import paper_metrics, paper_metrics_step
from tasks.evaluation.video_quality import vfi_smoothness
from tasks.reporting.video_tables import PAPER_COLUMNS, paper_metric_reasons, table1
from tests.evaluation.videos import noise_video

TINY_MUSIQ = MusiqConfig(token_dim=8, hidden_size=16, mlp_dim=32, num_heads=1, num_layers=2)
TINY_AMT = AmtConfig(channels=(8, 12, 16, 20), skip_channels=4, encoder_widths=(8, 16, 24), feature_dim=16,
                     hidden_dim=16, flow_dim=4, corr_dim=8, fc_dim=8)
MUSIQ_URL = "https://github.com/chaofengc/IQA-PyTorch/releases/download/v0.1-weights/musiq_spaq_ckpt-358bb6af.pth"
AMT_URL = "https://huggingface.co/lalala125/AMT/resolve/main/amt-s.pth"


pytestmark = pytest.mark.usefixtures("torch_one_thread")


def _musiq_file(tmp_path):
    torch.manual_seed(0)
    path = tmp_path / "musiq_spaq_ckpt-358bb6af.pth"
    torch.save(MUSIQ(TINY_MUSIQ).state_dict(), path)  # IQA-PyTorch's format: a flat state dict
    return path


def _amt_file(tmp_path):
    torch.manual_seed(0)
    path = tmp_path / "amt-s.pth"
    torch.save({"state_dict": AMT(TINY_AMT).state_dict()}, path)  # the AMT release's format
    return path


def test_published_musiq_and_amt_s_have_the_released_checkpoints_parameter_names_and_sizes():
    musiq = MUSIQ().state_dict()
    assert len(musiq) == 248 and sum(v.numel() for v in musiq.values()) == 27_125_825
    assert {"conv_root.weight", "gn_root.bias", "block1.conv_proj.weight", "block1.gn_proj.weight",
            "embedding.weight", "transformer_encoder.posembed_input.position_emb",
            "transformer_encoder.scaleembed_input.scale_emb", "transformer_encoder.cls",
            "transformer_encoder.transformer.encoderblock_13.attention.query.bias",
            "transformer_encoder.transformer.encoderblock_13.mlp.fc2.weight",
            "transformer_encoder.encoder_norm.weight", "head.weight"} <= set(musiq)
    assert MusiqConfig.from_state_dict(musiq) == MusiqConfig()
    amt = AMT().state_dict()
    assert len(amt) == 213 and sum(v.numel() for v in amt.values()) == 2_990_543
    assert {"feat_encoder.layer2.0.downsample.0.weight", "encoder.pyramid4.1.1.weight",
            "decoder4.convblock.1.conv2.0.weight", "decoder1.convblock.2.weight", "update2.flow_head.2.weight",
            "comb_block.1.weight"} <= set(amt)
    assert AmtConfig.from_state_dict(amt) == AmtConfig()


def test_tiny_musiq_round_trips_through_the_loader_and_scores_a_video_deterministically(tmp_path):
    path = _musiq_file(tmp_path)
    net = load_musiq(path)
    assert net.config == TINY_MUSIQ and not net.training
    saved = torch.load(path, weights_only=True)
    assert all(torch.equal(saved[k], v) for k, v in net.state_dict().items())
    video = noise_video(3, 96, 160)
    scores = musiq_frame_scores(video, net)
    assert scores.shape == (3,) and np.isfinite(scores).all()
    np.testing.assert_array_equal(scores, musiq_frame_scores(video, load_musiq(path)))
    # VBench's resize: a frame whose longer side exceeds 512 px is scored at 512 px (here 1024 x 640 -> 512 x 320)
    big = np.repeat(np.repeat(video[:1], 2, axis=1), 2, axis=2)
    big = np.pad(big, ((0, 0), (0, 448), (0, 704), (0, 0)))
    assert np.isfinite(musiq_frame_scores(big, net)).all()


def test_tiny_amt_round_trips_through_the_loader_and_interpolates_deterministically(tmp_path):
    path = _amt_file(tmp_path)
    net = load_amt(path)
    assert net.config == TINY_AMT and not net.training
    video = noise_video(2, 128, 136)  # 136 px is not a multiple of 16: the replicate-padding path
    mid = amt_midpoint(net, video[0], video[1])
    assert mid.shape == video[0].shape and mid.dtype == np.uint8
    np.testing.assert_array_equal(mid, amt_midpoint(load_amt(path), video[0], video[1]))


def test_the_vbench_smoothness_arithmetic():
    video = noise_video(5, 16, 16)
    exact = {(0, 2): video[1], (2, 4): video[3]}
    assert vfi_smoothness(video, lambda a, b: exact[(_index(video, a), _index(video, b))]) == 1.0
    off = {k: np.clip(v.astype(int) + 51, 0, 255).astype(np.uint8) for k, v in exact.items()}
    expected = (255.0 - np.mean([np.abs(off[k].astype(int) - exact[k]).mean() for k in exact])) / 255.0
    assert vfi_smoothness(video, lambda a, b: off[(_index(video, a), _index(video, b))]) == pytest.approx(expected)


def _index(video: np.ndarray, frame: np.ndarray) -> int:
    return next(i for i in range(len(video)) if np.array_equal(video[i], frame))


def test_absent_weights_give_the_report_line_naming_what_to_fetch_and_where(tmp_path):
    cfg = {"musiq_weights": None, "amt_weights": str(tmp_path / "nowhere" / "amt-s.pth"), "views": "all"}
    values, reasons, frame_scores, seconds = paper_metrics(noise_video(5, 128, 144)[None], cfg)
    assert all(math.isnan(v) for v in values.values()) and frame_scores is None and seconds == {}
    assert reasons["imaging_quality_musiq"] == (
        "not computed: weights not present (paper_metrics.musiq_weights is not set; download "
        f"musiq_spaq_ckpt-358bb6af.pth from {MUSIQ_URL} and run with "
        "paper_metrics.musiq_weights=/path/to/musiq_spaq_ckpt-358bb6af.pth)")
    assert reasons["motion_smoothness_amt"] == (
        f"not computed: weights not present (no file at {tmp_path}/nowhere/amt-s.pth, named by "
        f"paper_metrics.amt_weights; download amt-s.pth from {AMT_URL} to that path)")
    assert reasons["physical_commonsense"] == (
        "not computed: weights not present (paper_metrics.videophy_weights is not set; download videophy_2_auto from "
        "https://huggingface.co/videophysics/videophy_2_auto and run with "
        "paper_metrics.videophy_weights=/path/to/videophy_2_auto)")
    # a run that named no weight file has no paper_metrics artifact: the report gives the "not set" lines
    lines = paper_metric_reasons({})
    assert lines["VBench imaging quality (MUSIQ, SPAQ)"] == reasons["imaging_quality_musiq"]
    assert lines["VBench motion smoothness (AMT-S)"].startswith("not computed: weights not present "
                                                                "(paper_metrics.amt_weights is not set; download")


def test_the_step_scores_the_final_video_with_the_tiny_stand_ins_and_the_report_takes_its_values(tmp_path):
    root = tmp_path / "artifacts"
    video = noise_video(5, 128, 128)
    g = write_artifact(root / "o/gbuffer/g.zarr", {"rgb": Array(video[None], ("view", "frame", "y", "x", "channel"),
                                                                "1")}, step="gbuffer", scope="o", config_digest="g",
                       root=root)
    e = write_artifact(root / "o/effect/e.zarr", {}, step="effect", scope="o", config_digest="e", root=root)
    params = {"paper_metrics": {"musiq_weights": str(_musiq_file(tmp_path)), "amt_weights": str(_amt_file(tmp_path)),
                                "views": "all", "weights_digest": None}, "render.device": "cpu"}
    ref = paper_metrics_step.run_local(root=str(root), scope="o", params=params, inputs={"gbuffer": g, "effect": e})
    from tasks.core.artifacts import read_artifact

    art = read_artifact(ref)
    metrics = art.attrs["metrics"]
    assert art["musiq_frame_score"].shape == (1, 5)
    assert metrics["imaging_quality_musiq"] == pytest.approx(art["musiq_frame_score"].mean() / 100.0)
    assert 0.0 <= metrics["motion_smoothness_amt"] <= 1.0 and metrics["physical_commonsense"] is None
    assert set(art.attrs["reasons"]) == {"physical_commonsense"}
    refs = {"o": {"variants": {"full": {"backends": {"physics": {"paper_metrics": ref}}}}}}
    assert set(paper_metric_reasons(refs)) == {"Physical commonsense (VideoPhy-2 / VideoCon-Physics)",
                                               "Human evaluation (1-5)"}
    import pandas as pd

    df = pd.DataFrame([{"object": "o", "variant": "full", "backend": "physics",
                        **{k: (math.nan if metrics[k] is None else metrics[k]) for k, _, _ in PAPER_COLUMNS}}])
    header, rows, _ = table1(df, {"full": "Full"}, {})
    assert rows[0][header.index("VBench imaging quality (MUSIQ, SPAQ)")] == f"{metrics['imaging_quality_musiq']:.3f}"


def test_the_step_runs_only_when_a_weight_file_is_named_and_preflight_keys_it_by_content(tmp_path, compose_cfg):
    from flows.pipeline import wanted
    from flows.preflight import preflight

    default = compose_cfg("squeeze", ["object=can"])
    assert not wanted(paper_metrics_step, default)  # the default run does no paper-metric work at all
    path = _musiq_file(tmp_path)
    cfg = compose_cfg("squeeze", ["object=can", f"paper_metrics.musiq_weights={path}"])
    assert wanted(paper_metrics_step, cfg)
    preflight(cfg)
    first = cfg.paper_metrics.weights_digest
    torch.save({k: v + 1 for k, v in torch.load(path, weights_only=True).items()}, path)  # new weights, same path
    cfg = compose_cfg("squeeze", ["object=can", f"paper_metrics.musiq_weights={path}"])
    preflight(cfg)
    assert first and cfg.paper_metrics.weights_digest and cfg.paper_metrics.weights_digest != first


def test_frames_too_small_for_amt_s_and_a_wrong_checkpoint_are_one_line_each(tmp_path):
    cfg = {"musiq_weights": None, "amt_weights": str(_amt_file(tmp_path)), "views": "view0"}
    values, reasons, _, _ = paper_metrics(noise_video(3, 96, 160)[None], cfg)
    assert math.isnan(values["motion_smoothness_amt"])
    assert reasons["motion_smoothness_amt"] == ("not computed: frames of 160 x 96 px are below AMT-S's 128 px minimum "
                                                "after padding to multiples of 16 (render.width/height)")
    cfg["amt_weights"] = str(_musiq_file(tmp_path))  # a MUSIQ file named as the AMT-S checkpoint
    with pytest.raises(RuntimeError) as err:
        paper_metrics(noise_video(3, 128, 128)[None], cfg)
    assert str(err.value).startswith(f"paper_metrics.amt_weights: {cfg['amt_weights']} is not a loadable "
                                     "motion_smoothness_amt checkpoint (KeyError:")
    assert "\n" not in str(err.value)
