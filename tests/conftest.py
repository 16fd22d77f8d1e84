"""Shared fixtures: one Prefect test server for the session, Hydra composition, tmp artifact roots."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
_SESSION_TMP = Path(tempfile.mkdtemp(prefix="virsqueezer-tests-"))
# Prefect reads its settings at import: point its home at a throwaway folder before anything imports it.
os.environ["VIRSQUEEZER_ARTIFACTS"] = str(_SESSION_TMP / "artifacts")
(_SESSION_TMP / "artifacts" / ".prefect").mkdir(parents=True)
os.environ.setdefault("WARP_CACHE_PATH", str(Path.home() / ".cache" / "warp"))

import flows  # noqa: E402,F401  (sets Prefect's defaults)


@pytest.fixture(scope="session")
def prefect_server():
    """A real Prefect API server shared by every flow test (one start-up instead of one per flow)."""
    from prefect.settings import PREFECT_API_URL
    from prefect.testing.utilities import prefect_test_harness

    with prefect_test_harness(server_startup_timeout=180):
        yield PREFECT_API_URL.value()


def compose(config_name: str, overrides: list[str]):
    """Compose a config exactly as the ``python -m flows.<name>`` entry point does (a study's or benchmark's:
    ``study/<name>``, as ``python -m flows.studies.<name>`` / ``flows.bench.<name>``)."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from conf.study.schema import register_study_configs

    register_study_configs()  # the pipeline's schema and every study's
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return hydra_compose(config_name=config_name, overrides=overrides)


@pytest.fixture
def compose_cfg():
    return compose


@pytest.fixture
def key_env(monkeypatch):
    """The test API key in its environment variable (tests/chat_endpoint.py): the name a client config points to."""
    from tests.chat_endpoint import KEY_ENV, SECRET

    monkeypatch.setenv(KEY_ENV, SECRET)
    return KEY_ENV


@pytest.fixture(scope="module")
def torch_one_thread():
    """Torch on one thread (VIRSQUEEZER_TORCH_THREADS) for a module: fast on the shared 2-core machine."""
    import torch

    previous = torch.get_num_threads()
    torch.set_num_threads(int(os.environ.get("VIRSQUEEZER_TORCH_THREADS", "1")))
    yield
    torch.set_num_threads(previous)
