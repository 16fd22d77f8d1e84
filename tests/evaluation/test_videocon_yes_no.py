"""VideoCon-Physics' physical commonsense on the paper's [0, 1] scale (issue 45): P(Yes) / (P(Yes) + P(No)) of the
next token after VideoPhy's physics question, on the tiny mPLUG-Owl-Video stand-in saved as a release folder.  A
stand-in made to answer "Yes" scores above 0.5 and above the same stand-in made to answer "No"; the 1-5 rating
parser reads either answer as 0 (why a VideoCon folder scored 0 before)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from tasks.evaluation.videophy import (
    PROMPT_PHYSICS,
    PROMPT_VIDEOCON,
    load_videophy,
    parse_rating,
    share_rated_at_least,
    video_pixels,
)
from tests.evaluation.tiny_rater import save_rater, word_tokenizer
from tests.evaluation.videos import noise_video


def _release(tmp_path):
    folder = tmp_path / "videocon_physics"
    save_rater(folder, word_tokenizer(PROMPT_PHYSICS + PROMPT_VIDEOCON, {"Yes", "No"}))
    return folder


def _answering(rater, video: np.ndarray, word: str) -> None:
    """Make the stand-in's next token after the prompt ``word`` ("Yes" or "No"): the lm-head rows of Yes and No set
    to +-10 / |h| times the direction of the final hidden state h at the prompt's last position."""
    pixels = video_pixels(video, rater.frames, rater.net.cfg.vision["image_size"])
    with torch.no_grad():
        embeds = rater.net.prompt_embeddings(rater.prompt_ids(PROMPT_VIDEOCON), pixels)
        h = rater.net.language_model(inputs_embeds=embeds, output_hidden_states=True).hidden_states[-1][0, -1]
        yes, no = (rater.tokenizer.encode(w, add_special_tokens=False)[0] for w in ("Yes", "No"))
        sign = 1.0 if word == "Yes" else -1.0
        head = rater.net.language_model.lm_head.weight
        head[yes] = sign * 10.0 * h / h.norm() ** 2
        head[no] = -sign * 10.0 * h / h.norm() ** 2


@pytest.fixture(autouse=True)
def _one_thread():
    torch.set_num_threads(1)


def test_a_yes_answer_scores_above_a_no_answer_on_the_zero_one_scale(tmp_path):
    folder, video = _release(tmp_path), noise_video(40, 48, 64)
    scores, answers = {}, {}
    for word in ("Yes", "No"):
        rater = load_videophy(folder, frames=4, dtype=torch.float32)
        _answering(rater, video, word)
        scores[word] = rater.p_yes(video)
        ids = rater.prompt_ids(PROMPT_VIDEOCON)
        with torch.no_grad():
            embeds = rater.net.prompt_embeddings(ids, video_pixels(video, 4, 28))
            first = rater.net.language_model(inputs_embeds=embeds).logits[0, -1].argmax()
        answers[word] = rater.tokenizer.decode([int(first)])
    assert answers == {"Yes": "Yes", "No": "No"}  # the greedy answer of each stand-in
    assert scores["Yes"] > 0.99 and scores["No"] < 0.01 and scores["Yes"] > scores["No"]
    # logits +10 and -10: P(Yes) / (P(Yes) + P(No)) = 1 / (1 + e^-20) for the "Yes" stand-in
    assert scores["Yes"] == pytest.approx(1 / (1 + np.exp(-20.0)), abs=1e-6)
    assert parse_rating("Yes") == parse_rating("No") == 0  # the 1-5 parser cannot read a Yes / No answer


def test_videophy2_share_rated_four_or_more():
    assert share_rated_at_least([5, 4, 3, 1]) == 0.5 and share_rated_at_least([3, 3]) == 0.0
    assert np.isnan(share_rated_at_least([]))
