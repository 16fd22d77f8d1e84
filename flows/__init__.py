"""Hydra-configured Prefect flows.  Importing this package sets Prefect's offline defaults first.

Prefect reads its settings when it is imported, so they are set here, before any flow module imports it:
``PREFECT_HOME`` under the artifacts folder, analytics off, and a server start-up timeout that survives a
slow 2-core machine.  Variables already set in the environment win (e.g. ``PREFECT_API_URL`` of a
long-lived ``prefect server start``).
"""
import os as _os

_root = _os.path.abspath(_os.environ.get("VIRSQUEEZER_ARTIFACTS", "artifacts"))
for _key, _value in {
    "PREFECT_HOME": _os.path.join(_root, ".prefect"),
    "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
    "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS": "180",
    "PREFECT_LOGGING_LOG_PRINTS": "true",
    "PREFECT_RESULTS_PERSIST_BY_DEFAULT": "true",
    "PREFECT_RESULTS_LOCAL_STORAGE_PATH": _os.path.join(_root, ".prefect", "results"),
}.items():
    _os.environ.setdefault(_key, _value)
