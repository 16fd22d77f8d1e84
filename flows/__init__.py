"""Hydra-configured Prefect flows.  Importing this package sets Prefect's offline defaults first.

Prefect reads its settings when it is imported, so they are set here, before any flow module imports it:
``PREFECT_HOME`` under the artifacts folder, analytics off, and a server start-up timeout that survives a
slow 2-core machine.  Variables already set in the environment win (e.g. ``PREFECT_API_URL`` of a
long-lived ``prefect server start``).  The artifacts folder here is ``$VIRSQUEEZER_ARTIFACTS`` or
``./artifacts`` (code that imports the flows, e.g. tests); a Hydra main moves ``PREFECT_HOME`` and the cache
records to its ``paths.artifacts`` before Prefect is imported (:func:`flows.lifecycle.begin_run`), unless the
user set them.  Two flow processes started at once on one artifacts folder do not share the database of their
temporary servers (see :func:`flows.runtime.prefect_database_settings`).
"""
import os as _os

# the Prefect paths the user set: a main leaves them alone (the others follow its paths.artifacts)
USER_PREFECT_PATHS = frozenset(k for k in ("PREFECT_HOME", "PREFECT_RESULTS_LOCAL_STORAGE_PATH") if k in _os.environ)
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
# PREFECT_HOME is created (with its parents) where it is used: flows.lifecycle, before the server starts
