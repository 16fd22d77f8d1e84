"""Paper sec. 3.2, squeezing-driven deformation: the material oracle, the MPM rollout (eqs. 4-5) with its shared measures (regions, labels, wall resolution) and the MLS-MPM engine in ``mpm/``."""
