"""The schema of the interactive 4D viewer (``python -m flows.view``): the pipeline's config (the evaluation grid's,
``conf/evaluate.yaml``, whose cached artifacts it reads) plus the viewer's own keys at the root."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from conf.schema import Config


@dataclass
class ViewConfig(Config):
    """``python -m flows.view object=tomato [variant=full] [seed=1] [compare=no_dirichlet] [port=8080]``.

    seed: the sampling seed of the run shown (None: ``sampling.seed``).  compare: a second variant of
    ``variants`` drawn beside the first at the same instant (None: the first alone).  host, port: where the viser
    server listens (loopback by default; port 0 = a free port).  record: also write a self-contained HTML
    recording of the squeeze (plays without a Python server) to ``recording`` (None:
    ``<paths.reports>/viewer/<object>_<variant>.html``) and exit.  speed: playback rate at start (1 = real time).
    """

    seed: Optional[int] = None
    compare: Optional[str] = "no_dirichlet"
    host: str = "127.0.0.1"
    port: int = 8080
    record: bool = False
    recording: Optional[str] = None
    speed: float = 1.0


def register_view_config() -> None:
    """Register :class:`ViewConfig` as ``view_schema`` (and the pipeline's ``config_schema``)."""
    from hydra.core.config_store import ConfigStore

    from conf.schema import register_configs

    register_configs()
    ConfigStore.instance().store(name="view_schema", node=ViewConfig)
