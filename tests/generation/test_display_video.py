"""The watched videos draw the hand; the method never sees it: with ``render.hand`` on and off the G-buffer of eq. 6,
the conditions, the effect frames and every metric are bit-identical, while the display frames differ where the hand
is drawn (a real chain on a small tomato, the G-buffer steps recomputed for the second setting)."""
from __future__ import annotations

import shutil

import numpy as np

from tests.small_runs import SMALL

COMPARED = ("gbuffer", "conditions", "effect", "appearance_refinement", "video_metrics", "deformation_metrics")


def test_the_hand_changes_the_watched_video_and_nothing_the_method_or_the_metrics_compute(tmp_path):
    from flows.pipeline import run_object_local
    from tasks.core.artifacts import read_artifact
    from tests.conftest import compose

    def chain(root, hand: bool):
        cfg = compose("evaluate", [f"paths.artifacts={root}", "object=tomato", "variant=full", *SMALL,
                                   f"render.hand={str(hand).lower()}"])
        return run_object_local(cfg, cfg.object, cfg.variant, root)

    on = chain(tmp_path / "on", True)
    shutil.copytree(tmp_path / "on", tmp_path / "off")  # the physics is reused, the render steps run again
    off = chain(tmp_path / "off", False)
    assert off["mpm_rollout"].reused and not off["gbuffer"].reused  # render.hand is in the G-buffer's key
    for step in COMPARED:
        a, b = read_artifact(on[step]), read_artifact(off[step])
        assert set(a.arrays) == set(b.arrays), step
        for name in a.arrays:
            np.testing.assert_array_equal(a[name], b[name], err_msg=f"{step}/{name}")
        assert a.attrs == b.attrs, step
    shown, plain = read_artifact(on["display_video"]), read_artifact(off["display_video"])
    differs = (shown["frames"] != plain["frames"]).any(axis=-1)
    assert differs.mean() > 0.02  # the hand covers part of every view
    assert differs.reshape(len(differs), -1).any(axis=1).all()  # in every view, the close-up included
    assert shown.attrs["hand"] and not plain.attrs["hand"]
