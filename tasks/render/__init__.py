"""Rendering stage (paper sec. 3.2, last paragraph; sec. 3.3, eq. 6): G-buffer of the simulated splats and the
conditions derived from it."""
