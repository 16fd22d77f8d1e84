"""Hydra-configured Prefect flows.  Importing this package sets Prefect's offline defaults first.

Prefect reads its settings when it is imported, so they are set here, before any flow module imports it:
``PREFECT_HOME`` under the artifacts folder, analytics off, and a server start-up timeout that survives a
slow 2-core machine.  Variables already set in the environment win (e.g. ``PREFECT_API_URL`` of a
long-lived ``prefect server start``).  Two flow processes started at once on one artifacts folder do not
share the database of their temporary servers (see :func:`flows.runtime.prefect_database_settings`).
"""
import os as _os

_root = _os.path.abspath(_os.environ.get("VIRSQUEEZER_ARTIFACTS", "artifacts"))
for _key, _value in {
    "PREFECT_HOME": _os.path.join(_root, ".prefect"),
    "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
    "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS": "180",
    "PREFECT_LOGGING_LOG_PRINTS": "true",
    "PREFECT_RESULTS_PERSIST_BY_DEFAULT": "true",
    # whatever Prefect persists (e.g. a failed flow's exception) is JSON: nothing under artifacts/ is a pickle
    "PREFECT_RESULTS_DEFAULT_SERIALIZER": "json",
    "PREFECT_RESULTS_LOCAL_STORAGE_PATH": _os.path.join(_root, ".prefect", "results"),
    # transformers (imported by diffusers) logs optional-package hints at import: keep the run's output to ours
    "TRANSFORMERS_VERBOSITY": "error",
    "HF_HUB_OFFLINE": "1",  # nothing is downloaded at run time
}.items():
    _os.environ.setdefault(_key, _value)
# Prefect creates its home without parents (a new artifacts folder would leave its server without a database)
_os.makedirs(_os.environ["PREFECT_HOME"], exist_ok=True)
