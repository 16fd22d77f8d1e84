"""One object through the pipeline:  ``python -m flows.squeeze object=tomato``."""
import hydra
from omegaconf import DictConfig

from conf.schema import register_configs

register_configs()


@hydra.main(version_base="1.3", config_path="../conf", config_name="squeeze")
def main(cfg: DictConfig) -> None:
    from flows.lifecycle import begin_run

    begin_run(cfg.paths.artifacts)  # Prefect's home under paths.artifacts, Ctrl-C handling; before Prefect loads
    from flows.preflight import preflight

    preflight(cfg)  # bad config or input: one line, before the engine, Prefect or a server is loaded
    from flows.pipeline import run

    run(cfg, "squeeze")


if __name__ == "__main__":
    main()
