"""The default grid's hollow rubber ball as the rollout builds it, for the ball study (``python -m
flows.studies.ball``) and the membrane tests: its MPM scene from the object model and material oracle artifacts,
and the study's table rows.

The ball is squeezed between two frictionless flats (:func:`tasks.verification.contact.body_between_flats`) and
compared with the axisymmetric finite-strain FE of the same hollow sphere (:func:`tasks.verification.sphere_fe.
sphere_between_flats`).  Forces in N, lengths in m (the tables print mm), times in s.
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from tasks.core.artifacts import read_artifact
from tasks.physics.rollout_scene import build_scene

# the pipeline overrides of every ball run: the full variant, no gravity, no energy guard (the flats are not the
# eq. 3 field the guard's budget counts)
BALL_OVERRIDES = ("object=rubber_ball", "variant=full", "mpm.gravity=[0,0,0]", "mpm.energy_guard_tolerance=0")
UNTIL = "material_oracle"  # the last pipeline step the scene needs
HOLD_MARKS = (1.0, 2.0, 5.0, 10.0, 20.0, 40.0)  # s: when the held force is reported (those within the hold)


def ball_scene(refs: Mapping[str, Any], params: Mapping[str, Any]):
    """The rollout's scene (:func:`tasks.physics.rollout_scene.build_scene`, grid-node fingers) of the object whose
    artifacts up to the material oracle (the object model and its MPM particles among them) are ``refs`` (step name -> ArtifactRef), with the rollout step's ``params``
    (``mpm``, ``simulation``).  A wall sampled in Gauss layers but held as a 3D solid (``mpm.thin_walls=solid``, or
    thicker than ``mpm.membrane_max_thickness`` of a cell) touches the flats at its faces as the plane-stress wall
    does, not half a particle spacing out."""
    a = {k: read_artifact(v) for k, v in refs.items()}
    model, particles = a["object_model"], a["mpm_particles"]
    return build_scene({**model.arrays, **particles.arrays}, {**model.attrs, **particles.attrs, "name": model.ref.scope},
                       a["dirichlet_field"].arrays,
                       a["contact_patches"].arrays, a["signal_smoothing"]["time"],
                       a["material_oracle"].attrs["materials"], params["mpm"], params["simulation"],
                       a["force_coefficients"]["force_coefficients"], "dirichlet")


def force_row(name: str, force: np.ndarray, note: str) -> str:
    """One markdown table row: the run, its force per flat (N) at each mark, a note."""
    return f"| {name} | " + " | ".join(f"{v:.2f}" for v in force) + f" | {note} |"


def hold_marks(hold: float) -> np.ndarray:
    """The times (s) of the held-force table: the ``HOLD_MARKS`` within ``hold`` and ``hold`` itself."""
    return np.array([t for t in HOLD_MARKS if t <= hold] + ([hold] if hold not in HOLD_MARKS and hold > 0 else []))
