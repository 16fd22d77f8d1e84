"""The eight-object evaluation grid:  ``python -m flows.evaluate``  (``-m`` for sweeps)."""
import sys
from typing import Callable

import hydra
from omegaconf import DictConfig

from conf.schema import register_configs

register_configs()


def pipeline_main(config_name: str) -> Callable[..., None]:
    """The Hydra main of a pipeline flow composed from ``conf/<config_name>.yaml`` (the flow's label, too)."""
    @hydra.main(version_base="1.3", config_path="../conf", config_name=config_name)
    def main(cfg: DictConfig) -> None:
        from flows.sweep_summary import sweep_job

        with sweep_job():  # in a -m sweep: a failing job is recorded and the others go on
            from flows.lifecycle import begin_run

            # Prefect's home under paths.artifacts (paths.reports for a read-only cache), Ctrl-C handling; before Prefect
            begin_run(cfg.paths.artifacts, cfg.paths.reports)
            from flows.preflight import preflight

            preflight(cfg, read_only_ok=True)  # bad config or input: one line, before Prefect or a server loads
            from flows.pipeline import run

            run(cfg, config_name)

    def checked_main() -> None:
        from flows.hydra_checks import check_argv
        from flows.override_quoting import check_override_quoting

        check_argv(sys.argv[1:], f"flows.{config_name}")  # -m after the overrides: a usage line, not argparse's
        check_override_quoting(sys.argv[1:])  # a non-ASCII path unquoted: the quoting, not Hydra's lexer error
        main()

    return checked_main


main = pipeline_main("evaluate")

if __name__ == "__main__":
    main()
