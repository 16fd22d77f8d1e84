"""Configs of the studies and benchmarks (``flows/studies/``, ``flows/bench/``): ``<name>.yaml`` and their schemas."""
