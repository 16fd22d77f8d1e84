"""Export one object's 4D result as 3DGS PLY files, one per rendered frame:

    python -m flows.export object=tomato                       # variant full, the configured effect backend
    python -m flows.export object=can variant=no_dirichlet paths.export=/tmp/can_ply

Runs (or, with the same config, reuses from ``artifacts/``) the object's steps without Prefect, then writes
``<out>/frame_XXXX.ply`` (default ``reports/ply/<object>_<variant>/``).  From a read-only artifacts cache it only
reads: every step must be cached there (else one line naming the first that is not).  No computation lives here.
"""
from pathlib import Path

import hydra
import numpy as np
from omegaconf import DictConfig

from conf.schema import register_configs

register_configs()


@hydra.main(version_base="1.3", config_path="../conf", config_name="squeeze")
def main(cfg: DictConfig) -> None:
    from flows.lifecycle import begin_run

    # Prefect's home under paths.artifacts (paths.reports for a read-only cache), Ctrl-C handling; before Prefect loads
    begin_run(cfg.paths.artifacts, cfg.paths.reports)
    from flows.preflight import preflight

    preflight(cfg, read_only_ok=True)
    from flows.pipeline import run_object_local, shared_cache_object
    from flows.preflight_env import read_only_cache
    from tasks.core.artifacts import read_artifact
    from tasks.generation.ply_sequence import write_ply_sequence
    from tasks.render.scene import drawn_covariances

    why, until = read_only_cache(cfg.paths.artifacts), "appearance_refinement"
    refs = (shared_cache_object(cfg, cfg.object, cfg.variant, why, until) if why  # found there, nothing run or written
            else run_object_local(cfg, cfg.object, cfg.variant, cfg.paths.artifacts, until=until))
    obj, rollout, g, refined = (read_artifact(refs[k]) for k in ("object_model", "mpm_rollout", "gbuffer",
                                                                   "appearance_refinement"))
    frames = g["frame_index"]
    if "released_index" in refined:  # eq. 7's refined appearance of the released particles
        index = refined["released_index"]
        colors, opacities, scales = refined["released_color"], refined["released_opacity"], refined["released_scale"]
    else:  # nothing released (or no effect): the surface alone
        index = np.zeros(0, int)
        colors, opacities, scales = np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3))
    out = Path(cfg.paths.export or Path(cfg.paths.reports) / "ply" / f"{cfg.object.name}_{cfg.variant.name}")
    covariances = drawn_covariances(rollout["gaussian_covariances"][frames], obj["gaussian_scales"])  # as rendered
    paths = write_ply_sequence(out, rollout["gaussian_positions"][frames], covariances,
                               obj["gaussian_colors"], obj["gaussian_opacities"],
                               rollout["particle_positions"][frames][:, index], g["released_visible"][:, index],
                               colors, opacities, scales, frames)
    print(f"{len(paths)} PLY files ({len(index)} released particles) in {out}")


if __name__ == "__main__":
    main()
