"""The test suite: one folder per stage of tasks/ (core, control, physics, render, generation, evaluation,
verification, reporting) and flows/ for the wiring."""
