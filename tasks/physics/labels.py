"""Particle labels of an MPM rollout (the ``particle_material`` array): what each simulated particle is."""

SHELL, INTERIOR, RUPTURED, CORE = 0, 1, 2, 3
N_LABELS = 4
LABEL_NAMES = {SHELL: "shell", INTERIOR: "interior (released juice / cola / stuffing)", RUPTURED: "ruptured shell",
               CORE: "core (pulp / stuffing: part of the body)"}
