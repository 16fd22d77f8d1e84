"""Step framework: declaration and caching of method steps (step.py), their config parameters (params.py), code versions (code_version.py) and the zarr artifact store (artifacts.py)."""
