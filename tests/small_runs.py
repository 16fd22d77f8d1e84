"""The smallest real pipeline runs, shared by the tests that run whole flows (tests/flows, tests/reporting): Hydra
overrides that shrink the grid to seconds per step, and the content digests of the artifacts a run leaves."""
from __future__ import annotations

from pathlib import Path

from tasks.core.artifacts import read_group_attrs

# the per-object control chain (object model -> dirichlet_field) on a coarse sampling: seconds per step
CONTROL_SIZES = ["sampling.surface_points=600", "sampling.particle_spacing=0.004", "signal.duration=1.5",
                 "control.smoothing.frame_rate=15"]
# two 32 x 32 views of every fifth frame, two refinement iterations, the cheap video metrics
RENDER_SIZES = ["render.views=2", "render.width=32", "render.height=32", "render.frame_stride=5",
                "refinement.iterations=2", "video_metrics.interpolator=dis", "video_metrics.brisque_max_frames=2"]
# one variant, a short rollout, the sequential runner
SMALL = [*CONTROL_SIZES, "grid.variants=[full]", "mpm.target_substeps_per_frame=10", "runner=sequential",
         *RENDER_SIZES]


def artifact_digests(root: Path) -> dict[tuple[str, str, str], str]:
    """(scope, step, group) -> content digest of every artifact group under ``root / "artifacts"``."""
    return {(g.parent.parent.name, g.parent.name, g.name): read_group_attrs(g)["digest"]
            for g in (root / "artifacts").glob("*/*/*.zarr")}
