"""Suites that check the solver and the presets - stability, convergence (error against run time), the Taichi MLS-MPM benchmark peer.  Run by their own flows; never pipeline steps."""
