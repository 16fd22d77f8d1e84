"""Research studies and maintainer suites, each a Hydra main with its own config under ``conf/study/``.

``python -m flows.studies.<name>``: ``ball`` (the rubber ball against its finite-element reference), ``fingers``
(finger modes on Table 2), ``contact`` (contact against closed forms), ``convergence`` (error against run time),
``stability`` (the numerical stability suite), ``render_convergence`` (render and effect knobs).  Each only wires:
the computation lives in :mod:`tasks.verification`.
"""
