"""VideoPhy-2's physical-commonsense rater (our mPLUG-Owl-Video): a tiny randomly initialised stand-in saved in the
release folder layout (``config.json``, safetensors weights, tokenizer files from an in-memory ``tokenizers``
tokenizer) and loaded strictly through :func:`load_videophy`.  Random weights say nothing about physics: only shapes,
determinism, loading, key names and the recipe's arithmetic (frame choice, prompt, parse) are tested."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from tasks.evaluation.videophy import (
    PROMPT_PHYSICS,
    frame_indices,
    load_videophy,
    parse_rating,
    video_pixels,
)
from tests.evaluation.tiny_rater import QUERIES, save_rater, word_tokenizer
from tests.evaluation.videos import noise_video

pytestmark = pytest.mark.usefixtures("torch_one_thread")


def _release(tmp_path, seed: int = 0):
    """A tiny rater saved like the release folder; returns (folder, the network that was saved)."""
    folder = tmp_path / "videophy_2_autoeval"
    return folder, save_rater(folder, word_tokenizer(PROMPT_PHYSICS), seed)


def test_release_names_match_the_published_module_tree(tmp_path):
    folder, net = _release(tmp_path)
    keys = set(net.state_dict())
    for key in ("vision_model.embeddings.cls_token", "vision_model.embeddings.patch_embed.weight",
                "vision_model.embeddings.position_embedding", "vision_model.embeddings.pre_layernorm.weight",
                "vision_model.encoder.layers.1.temporal.conv.weight", "vision_model.encoder.layers.0.temporal.ln.bias",
                "vision_model.encoder.layers.0.self_attn.query_key_value.weight",
                "vision_model.encoder.layers.0.mlp.fc2.bias", "vision_model.post_layernorm.weight",
                "query_tokens", "temporal_query_tokens",
                "abstractor.encoder.layers.1.crossattention.attention.key.weight",
                "abstractor.encoder.layers.0.crossattention.output.mlp.ffn_ln.weight",
                "abstractor.encoder.layers.0.crossattention.normk.bias", "abstractor.temporal_visual_fc.weight",
                "abstractor.vit_eos", "language_model.model.layers.1.self_attn.q_proj.weight",
                "language_model.lm_head.weight"):
        assert key in keys, key
    assert "vision_model.embeddings.patch_embed.bias" not in keys  # the released patch convolution has no bias
    # the released SwiGLU width: 2/3 of intermediate_size rounded up to a multiple of 256
    assert net.abstractor.encoder.layers[0].crossattention.output.mlp.w1.weight.shape == (256, 32)


def test_loads_strictly_round_trip_and_rejects_a_renamed_key(tmp_path):
    from safetensors.torch import load_file, save_file

    folder, net = _release(tmp_path)
    rater = load_videophy(folder, frames=4, dtype=torch.float32)
    loaded = rater.net.state_dict()
    assert loaded.keys() == net.state_dict().keys()
    assert all(torch.equal(loaded[k], v) for k, v in net.state_dict().items())
    state = load_file(folder / "model.safetensors")
    state["abstractor.vit_eos_renamed"] = state.pop("abstractor.vit_eos")
    save_file(state, folder / "model.safetensors")
    with pytest.raises(RuntimeError, match="abstractor.vit_eos"):
        load_videophy(folder, frames=4, dtype=torch.float32)


def test_rating_shapes_determinism_and_range(tmp_path):
    folder, _ = _release(tmp_path)
    rater = load_videophy(folder, frames=4)  # bfloat16, as VideoPhy-2 runs it
    assert rater.net.language_model.lm_head.weight.dtype == torch.bfloat16
    ids = rater.prompt_ids()
    assert ids[0] == rater.tokenizer.bos_token_id and ids.count(-2) == QUERIES + 1
    pixels = video_pixels(noise_video(40, 48, 64), 4, 28).bfloat16()
    assert pixels.shape == (1, 3, 4, 28, 28)
    with torch.inference_mode():
        assert rater.net.video_embeddings(pixels).shape == (1, QUERIES + 1, 32)
        assert rater.net.prompt_embeddings(ids, pixels).shape == (1, len(ids), 32)
    first, second = rater.rate(noise_video(40, 48, 64)), rater.rate(noise_video(40, 48, 64))
    assert first == second
    assert 0 <= first[0] <= 5 and isinstance(first[1], str)
    # the video matters: another video changes the language model's input
    with torch.inference_mode():
        other = rater.net.video_embeddings(video_pixels(noise_video(40, 48, 64, seed=1), 4, 28).bfloat16())
        assert not torch.allclose(other, rater.net.video_embeddings(pixels))


def test_recipe_arithmetic():
    assert frame_indices(64, 32).tolist() == [int(63 / 64) + int(np.round(63 / 32 * i)) for i in range(32)]
    assert frame_indices(33, 4).tolist() == [4, 12, 20, 28]
    assert parse_rating("4") == 4 and parse_rating(" Five.") == 5 and parse_rating("no idea") == 0
    assert parse_rating("score: 3/5") == 3  # VideoPhy-2's parser takes the first listed match ("3" before "5")
    px = video_pixels(np.full((3, 10, 10, 3), 255, np.uint8), 2, 14)
    assert torch.allclose(px[0, :, 0, 0, 0], (1 - torch.tensor([0.48145466, 0.4578275, 0.40821073]))
                          / torch.tensor([0.26862954, 0.26130258, 0.27577711]), atol=1e-5)


def _sharded_release(tmp_path):
    """The tiny rater in the published file layout: two bfloat16 ``pytorch_model-0000?-of-00002.bin`` shards."""
    folder, net = _release(tmp_path)
    (folder / "model.safetensors").unlink()
    items = list(net.state_dict().items())
    for i, part in enumerate((items[::2], items[1::2]), start=1):
        torch.save({k: v.to(torch.bfloat16) for k, v in part}, folder / f"pytorch_model-0000{i}-of-00002.bin")
    return folder, net


def test_the_published_shard_layout_loads_in_bfloat16(tmp_path):
    folder, net = _sharded_release(tmp_path)
    loaded = load_videophy(folder, frames=4).net.state_dict()
    assert all(torch.equal(loaded[k], v.to(torch.bfloat16)) for k, v in net.state_dict().items())


def test_absent_or_broken_folder_gives_one_line_naming_the_key(tmp_path):
    from tasks.evaluation.paper_metrics import paper_metrics

    cfg = {"videophy_weights": str(tmp_path / "nowhere"), "views": "all"}
    values, reasons, _, seconds = paper_metrics(noise_video(40, 48, 64)[None], cfg)
    assert np.isnan(values["physical_commonsense"]) and seconds == {}
    assert reasons["physical_commonsense"] == (
        f"not computed: weights not present (no folder with a config.json at {tmp_path}/nowhere, named by "
        f"paper_metrics.videophy_weights; fetch it with `hf download videophysics/videophy_2_auto --local-dir "
        f"{tmp_path}/nowhere`)")
    folder, _ = _release(tmp_path)
    (folder / "model.safetensors").unlink()
    with pytest.raises(RuntimeError) as err:
        paper_metrics(noise_video(40, 48, 64)[None], {"videophy_weights": str(folder), "views": "all"})
    assert str(err.value) == (f"paper_metrics.videophy_weights: {folder} is not a loadable physical_commonsense "
                              f"checkpoint (FileNotFoundError: no *.safetensors or pytorch_model*.bin weights in "
                              f"{folder}); download the file named in the report again")


def test_the_step_rates_the_final_video_and_the_report_fills_the_column(tmp_path):
    from tasks.core.artifacts import Array, read_artifact, write_artifact
    from tasks.evaluation.paper_metrics import paper_metrics_step
    from tasks.reporting.video_tables import PAPER_COLUMNS, paper_metric_reasons, table1

    folder, _ = _sharded_release(tmp_path)
    root = tmp_path / "artifacts"
    rgb = Array(noise_video(6, 48, 64)[None], ("view", "frame", "y", "x", "channel"), "1")
    g = write_artifact(root / "o/gbuffer/g.zarr", {"rgb": rgb}, step="gbuffer", scope="o", config_digest="g", root=root)
    e = write_artifact(root / "o/effect/e.zarr", {}, step="effect", scope="o", config_digest="e", root=root)
    params = {"paper_metrics": {"videophy_weights": str(folder), "views": "all", "weights_digest": None},
              "render.device": "cpu"}
    ref = paper_metrics_step.run_local(root=str(root), scope="o", params=params, inputs={"gbuffer": g, "effect": e})
    attrs = read_artifact(ref).attrs
    share, rating = attrs["metrics"]["physical_commonsense"], attrs["metrics"]["physical_commonsense_rating"]
    assert rating in {0, 1, 2, 3, 4, 5} and "physical_commonsense" not in attrs["reasons"]
    assert share == (1.0 if rating >= 4 else 0.0)  # one scored view: the share rated >= 4 is 0 or 1
    assert attrs["seconds"]["physical_commonsense"] > 0
    refs = {"o": {"variants": {"full": {"backends": {"physics": {"paper_metrics": ref}}}}}}
    heading = "Physical commonsense [0, 1]: VideoPhy-2 autorater, share of videos rated >= 4"
    assert heading not in paper_metric_reasons(refs)
    import pandas as pd

    df = pd.DataFrame([{"object": "o", "variant": "full", "backend": "physics",
                        **{k: (np.nan if attrs["metrics"][k] is None else attrs["metrics"][k])
                           for k, _, _ in PAPER_COLUMNS}}])
    header, rows, _ = table1(df, {"full": "Full"}, {})
    assert rows[0][header.index(heading)] == f"{share:.3f}"
    assert rows[0][header.index("VideoPhy-2 autorater mean rating (1-5)")] == f"{rating:.3f}"


def test_only_a_named_folder_runs_the_step_and_preflight_keys_it(tmp_path, compose_cfg):
    from flows.pipeline import wanted
    from flows.preflight import preflight
    from tasks.evaluation.paper_metrics import paper_metrics_step

    assert not wanted(paper_metrics_step, compose_cfg("squeeze", ["object=can"]))
    folder, _ = _release(tmp_path)
    cfg = compose_cfg("squeeze", ["object=can", f"paper_metrics.videophy_weights={folder}"])
    assert wanted(paper_metrics_step, cfg)
    preflight(cfg)
    first = cfg.paper_metrics.weights_digest
    config = json.loads((folder / "config.json").read_text())
    (folder / "config.json").write_text(json.dumps({**config, "num_query_tokens": QUERIES}, indent=1))
    cfg = compose_cfg("squeeze", ["object=can", f"paper_metrics.videophy_weights={folder}"])
    preflight(cfg)
    assert first and cfg.paper_metrics.weights_digest and cfg.paper_metrics.weights_digest != first
