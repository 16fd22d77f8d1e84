"""VirSqueezer's code, grouped by the paper's stages (the executable index of steps is ``flows.pipeline.STEPS``).

core/          the step framework (declaration, cache key, code version) and the zarr artifact store
control/       sec. 3.1: object model, squeezing signals, smoothing, force coefficients (eq. 1), SC-CAE contact
               patches (eq. 2), displacement field / Dirichlet data (eq. 3)
physics/       sec. 3.2: material oracle, MPM rollout (eqs. 4-5) and the ``mpm/`` engine
render/        sec. 3.2-3.3: Gaussian rasteriser, G-buffer, the conditions of eq. 6
generation/    sec. 3.3: the secondary effect (diffusion or physics-rendered) and the 4D refinement of eq. 7
evaluation/    sec. 4: deformation metrics (Table 2) and video metrics (Tables 1, 3)
reporting/     the run report (tables, plots, videos)
verification/  suites that check the solver (stability, convergence, benchmark peer): never pipeline steps

Package ``__init__`` files hold only a docstring (``tests/flows/test_layering.py``), so that a step's code version is
exactly the import closure of its module.
"""
