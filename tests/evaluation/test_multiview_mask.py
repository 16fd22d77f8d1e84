"""Multi-view consistency on the refined mask only, before and after refinement (issue 45): a synthetic held-out
view whose error inside the mask is known gives the closed-form PSNR; frozen pixels outside the mask no longer
count (the former 8 px dilation inflated it), and the training views never enter the score."""
from __future__ import annotations

import math

import numpy as np
import pytest

from tasks.evaluation.video_metrics import video_metrics

CFG = {"smoothness_views": "view0", "interpolator": "dis", "brisque_max_frames": 2, "change_threshold": 0.05,
       "multiview_dilation_px": 0, "coupling_max_lag_frames": 1}


def _scene(after: int = 51, before: int = 102):
    """Two views x 4 frames of 48 x 48 px: the simulated render grey (100); the final video is the render with a
    12 x 12 px effect (the refined mask) painted 200; the refined Gaussians render the effect ``after`` sRGB levels
    off in every view, the initial ones ``before`` levels off, the training view 0 exactly right."""
    sim = np.full((2, 4, 48, 48, 3), 100, np.uint8)
    mask = np.zeros((2, 4, 48, 48), bool)
    mask[:, :, 18:30, 18:30] = True
    final = sim.copy()
    final[mask] = 200
    refined = final.copy()
    refined[1][mask[1]] = 200 - after
    initial = final[[1]].copy()
    initial[mask[[1]]] = 200 - before
    return final, sim, mask, refined, initial


def test_mask_only_psnr_is_the_closed_form_before_and_after_and_the_gain_is_their_difference():
    """sRGB error 51/255 = 0.2 on every masked pixel: PSNR = 10 log10(1 / 0.04) = 13.979 dB; before refinement
    0.4: 7.959 dB; gain 20 log10(2) = 6.021 dB.  The held-out view alone is scored (view 0, trained on, is exact
    and would read inf)."""
    final, sim, mask, refined, initial = _scene()
    values, reasons, _, _ = video_metrics(final, sim, mask, True, refined, [1], np.ones((4, 5)), [0], CFG, initial)
    assert values["multiview_psnr_db"] == pytest.approx(10 * math.log10(1 / 0.2 ** 2), abs=1e-5)
    assert values["multiview_psnr_db_initial"] == pytest.approx(10 * math.log10(1 / 0.4 ** 2), abs=1e-5)
    assert values["multiview_psnr_gain_db"] == pytest.approx(20 * math.log10(2), abs=1e-5)
    assert values["multiview_mae"] == pytest.approx(0.2, abs=1e-5)


def test_a_dilation_adds_frozen_pixels_and_inflates_the_psnr_by_the_area_ratio():
    """With an 8 px dilation the 12 x 12 mask grows to a 28 x 28 rounded square of pixels, the added ones identical
    in both images: MSE falls by the area ratio, the PSNR rises by 10 log10(area ratio) - what the default no longer
    does."""
    import cv2

    final, sim, mask, refined, initial = _scene()
    dilated = cv2.dilate(mask[1, 0].astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (17, 17)))
    ratio = dilated.sum() / mask[1, 0].sum()
    values, _, _, _ = video_metrics(final, sim, mask, True, refined, [1], np.ones((4, 5)), [0],
                                    {**CFG, "multiview_dilation_px": 8}, initial)
    assert ratio > 3
    assert values["multiview_psnr_db"] == pytest.approx(10 * math.log10(1 / 0.2 ** 2) + 10 * math.log10(ratio),
                                                        abs=1e-5)


def test_without_the_initial_render_the_before_and_gain_say_why():
    final, sim, mask, refined, _ = _scene()
    values, reasons, _, _ = video_metrics(final, sim, mask, True, refined, [1], np.ones((4, 5)), [0], CFG, None)
    assert math.isnan(values["multiview_psnr_db_initial"]) and math.isnan(values["multiview_psnr_gain_db"])
    assert "0-iteration" in reasons["multiview_psnr_gain_db"]
