"""Look at a squeeze from anywhere, in the browser:  ``python -m flows.view object=tomato``

    python -m flows.view object=plush_toy compare=null            # the full method alone
    python -m flows.view object=tomato variant=no_dirichlet seed=1 port=8081
    python -m flows.view object=tomato record=true                # a self-contained HTML recording, then exit

Starts a viser server on the loopback address (``host``, ``port``; conf/view_schema.py) and prints its URL.  It
reads only the artifacts ``python -m flows.evaluate`` cached (same config, same overrides, same keys: conf/view.yaml
is the grid's); when one is missing it says in one line which command makes it, and computes nothing.  The scene
is :mod:`tasks.reporting.viewer_scene`, the server :mod:`tasks.reporting.viewer`.  No computation lives here.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

from conf.view_schema import register_view_config

register_view_config()

SHOWN_UNTIL = "mpm_rollout"  # the last step whose artifact the viewer reads (per variant)


class ViewerInputError(RuntimeError):
    """The viewer cannot show what was asked (no object, an unknown variant, artifacts not cached): one line."""


def evaluate_command(overrides: list[str]) -> str:
    """The ``flows.evaluate`` command that caches what ``python -m flows.view <overrides>`` shows: the same
    overrides, ``seed`` as ``sampling.seed`` and ``compare`` as the grid's variants; the viewer's own keys dropped."""
    own = {"host", "port", "record", "recording", "speed"}
    args, variant, compare = [], "full", "no_dirichlet"
    for item in overrides:
        key, _, value = item.partition("=")
        if key == "variant":
            variant = value
        elif key == "compare":
            compare = value
        elif key == "seed":
            args.append(f"sampling.seed={value}")
        elif key not in own:
            args.append(item)
    variants = [variant] + ([compare] if compare not in ("null", "None", "", variant) else [])
    args.append(f"variant={variant}" if len(variants) == 1 else f"grid.variants=[{','.join(variants)}]")
    return " ".join(["python -m flows.evaluate", *args])


def load_scenes(cfg: DictConfig, overrides: list[str]) -> list:
    """The scenes shown (the variant, then the compared one), read from the cached artifacts; raises
    :class:`ViewerInputError` (one line, naming the command that caches them) when they are not on disk."""
    from flows.pipeline import NotCached, cached_object, with_seed
    from flows.preflight_env import read_only_cache
    from tasks.core.artifacts import read_artifact
    from tasks.core.scope import seed_scope
    from tasks.reporting.viewer_scene import squeeze_scene

    if cfg.object is None:
        raise ViewerInputError("object is not set: name the object to view, e.g. python -m flows.view object=tomato")
    names = [cfg.variant.name] + ([cfg.compare] if cfg.compare and cfg.compare != cfg.variant.name else [])
    unknown = [n for n in names[1:] if n not in cfg.variants]
    if unknown:
        raise ViewerInputError(f"compare={unknown[0]} is not a variant of this config ({sorted(cfg.variants)}): "
                               "use one of them or compare=null")
    variants = [cfg.variant] + [cfg.variants[n] for n in names[1:]]
    seed = int(cfg.sampling.seed if cfg.seed is None else cfg.seed)
    run_cfg = with_seed(cfg, seed)
    scope = seed_scope(cfg.object.name, seed)
    try:
        refs = cached_object(run_cfg, cfg.object, variants, scope, until=SHOWN_UNTIL,
                             discard=not read_only_cache(cfg.paths.artifacts))  # a read-only cache stays as it is
    except NotCached as missing:
        raise ViewerInputError(f"{missing} is not cached in {Path(cfg.paths.artifacts).resolve()}: run "
                               f"`{evaluate_command(overrides)}` first (the viewer computes nothing)") from None
    shared = {step: read_artifact(ref) for (step, chain), ref in refs.items() if chain == ""}
    render = OmegaConf.to_container(cfg.render, resolve=True)
    return [squeeze_scene({**shared, SHOWN_UNTIL: read_artifact(refs[(SHOWN_UNTIL, v.name)])}, render,
                          f"{scope} [{v.label or v.name}]") for v in variants]


def task_overrides() -> list[str]:
    """The command line's Hydra overrides (for the one-line message naming the command that caches them)."""
    from hydra.core.hydra_config import HydraConfig

    return list(HydraConfig.get().overrides.task) if HydraConfig.initialized() else []


def recording_path(cfg: DictConfig) -> Path:
    """Where ``record=true`` writes: ``recording``, else ``<paths.reports>/viewer/<scope>_<variant>.html`` (which
    the run reports in ``paths.reports`` link)."""
    from tasks.core.scope import seed_scope
    from tasks.reporting.viewer_scene import recording_name

    scope = seed_scope(cfg.object.name, int(cfg.sampling.seed if cfg.seed is None else cfg.seed))
    return Path(cfg.recording or Path(cfg.paths.reports) / "viewer" / recording_name(scope, cfg.variant.name))


@hydra.main(version_base="1.3", config_path="../conf", config_name="view")
def main(cfg: DictConfig) -> None:
    from flows import USER_PREFECT_PATHS
    from flows.lifecycle import follow_artifacts

    # the step modules import Prefect: its home there (under paths.reports when the artifacts are a read-only cache)
    follow_artifacts(cfg.paths.artifacts, USER_PREFECT_PATHS, cfg.paths.reports)
    try:
        scenes = load_scenes(cfg, task_overrides())
    except ViewerInputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    from tasks.reporting.viewer import SqueezeViewer

    viewer = SqueezeViewer(scenes, host=cfg.host, port=cfg.port, speed=cfg.speed)
    if cfg.record:
        path = viewer.record(recording_path(cfg), speed=cfg.speed)
        viewer.stop()
        print(f"recording: {path.resolve()} ({path.stat().st_size / 1e6:.1f} MB; opens in a browser, no server)")
        return
    print(f"viewer: {viewer.url}  ({', '.join(s.label for s in scenes)}; Ctrl-C to stop)", flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        viewer.stop()


if __name__ == "__main__":
    main()
