"""Benchmarks that print figures, each a Hydra main with its own config under ``conf/study/bench_<name>.yaml``.

``python -m flows.bench.mpm`` (our Warp MLS-MPM against a Taichi peer), ``python -m flows.bench.render`` (the
Gaussian rasteriser against its physical floor), ``python -m flows.bench.overhead`` (what one cached Prefect task
costs outside its step).
"""
