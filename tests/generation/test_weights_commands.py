"""The download commands we print are real ``hf download`` invocations (huggingface_hub 2.x; ``huggingface-cli`` is
gone): every command in the missing-weights message, the paper metrics' "not computed" lines and
``python -m flows.weights check`` is parsed by huggingface_hub's own CLI parser (click), without running it, and
fetches the repository, files or patterns, and folder the runs read."""
from __future__ import annotations

import re
import shlex

import click
import pytest

from flows.weights import inventory
from flows.weights import main as weights_main
from tasks.core.hub import hf_download_command
from tasks.evaluation.paper_weights import PAPER_WEIGHTS
from tasks.generation.components import DiffusionWeights, check_weights, missing_weights_message
from tests.generation.tiny_diffusion import save_diffusers_folders, tiny_components

DIFFUSERS_PATTERNS = ["*.json", "*.txt", "*model.safetensors"]


def parse_hf_download(command: str) -> dict:
    """The parameters huggingface_hub's ``hf`` CLI parses from ``command`` (click's ``make_context``: parsing and
    validation only, no download); click.UsageError when it is not a valid ``hf download``."""
    from huggingface_hub.cli.hf import app

    words = shlex.split(command)
    assert words[:2] == ["hf", "download"], command
    download = app.get_command(click.Context(app), "download")
    download = download.materialize() if hasattr(download, "materialize") else download
    return download.make_context("download", words[2:]).params


def _folder_commands(message: str) -> list[str]:
    return [line.split("): ", 1)[1] for line in message.splitlines()[1:]]


def test_the_parser_is_huggingface_hubs_own_and_catches_the_old_multi_pattern_form():
    params = parse_hf_download("hf download a/b --include '*.json' --include '*.txt' --local-dir /x")
    assert params["repo_id"] == "a/b" and list(params["include"]) == ["*.json", "*.txt"]
    # the huggingface-cli (argparse, nargs="*") form: hf reads the second pattern as a FILE name, and file names
    # make it ignore --include, so this would fetch one file literally named *.txt
    old = parse_hf_download("hf download a/b --include '*.json' '*.txt' --local-dir /x")
    assert list(old["filenames"]) == ["*.txt"]
    with pytest.raises(click.UsageError):
        parse_hf_download("hf download a/b --no-such-option 1")
    with pytest.raises(ValueError, match="ignores --include"):
        hf_download_command("a/b", "/x", files=("f.pth",), include=("*.json",))


def test_missing_diffusion_models_print_hf_download_commands_that_fill_the_folders_read(tmp_path):
    missing = check_weights(DiffusionWeights(folder=str(tmp_path)))
    commands = _folder_commands(missing_weights_message(missing))
    assert len(commands) == 3 and "huggingface-cli" not in missing_weights_message(missing)
    expected = [("stable-diffusion-v1-5/stable-diffusion-v1-5", "stable-diffusion"),
                ("guoyww/animatediff-motion-adapter-v1-5-2", "motion-adapter"),
                ("lllyasviel/control_v11f1p_sd15_depth", "controlnet-depth")]
    for command, (repo, folder) in zip(commands, expected):
        params = parse_hf_download(command)
        assert params["repo_id"] == repo and params["local_dir"] == str(tmp_path / folder)
        assert not params["filenames"] and list(params["include"]) == DIFFUSERS_PATTERNS
    assert list(parse_hf_download(commands[0])["exclude"]) == ["safety_checker/*"]


def test_paper_metric_lines_print_hf_download_commands_that_put_the_file_where_it_is_read(tmp_path):
    for spec in PAPER_WEIGHTS:
        for path in (None, str(tmp_path / spec.file)):
            command = re.search(r"`(hf download [^`]+)`", spec.reason(path)).group(1)
            params = parse_hf_download(command)
            assert params["repo_id"] == spec.hub.repo
            if spec.folder:  # the whole repository into the folder named
                assert not params["filenames"] and params["local_dir"] == str(tmp_path / spec.file if path
                                                                               else f"/path/to/{spec.file}")
            else:  # the one file, into the folder holding the path
                assert list(params["filenames"]) == [spec.file]
                assert params["local_dir"] == (str(tmp_path) if path else "/path/to")


def test_weights_check_lists_present_and_missing_models_with_parsable_commands(tmp_path, capsys):
    save_diffusers_folders(tiny_components(seed=0), DiffusionWeights(folder=str(tmp_path)))
    (tmp_path / "amt-s.pth").write_bytes(b"\0" * 1000)
    (tmp_path / "notes.txt").write_text("x")
    lines, complete = inventory(tmp_path)
    text = "\n".join(lines)
    assert not complete
    for name in ("an SD-1.5 base", "an AnimateDiff motion adapter", "a depth ControlNet",
                 "VBench motion smoothness (AMT-S)"):
        assert re.search(rf"present +{re.escape(name)}", text), name
    assert re.search(r"missing +VBench imaging quality", text) and re.search(r"missing +Physical commonsense", text)
    assert "other entries (not read by the runs): notes.txt" in text
    commands = [line.strip() for line in lines if line.strip().startswith("hf download")]
    assert [parse_hf_download(c)["repo_id"] for c in commands] == ["chaofengc/IQA-PyTorch-Weights",
                                                                    "videophysics/videophy_2_auto",
                                                                    "videophysics/videocon_physics"]
    assert (f"python -m flows.evaluate generation.weights={tmp_path} paper_metrics.amt_weights={tmp_path}/amt-s.pth"
            in text)
    assert weights_main(["check", str(tmp_path)]) == 1 and "weights folder" in capsys.readouterr().out
