"""MLS-MPM physics core (NVIDIA Warp): materials, constitutive models, kernels and the solver driver."""
from .materials import MODEL_CODES, Material, MaterialError, canonical_model, material_from_dict  # noqa: F401
from .solver import (  # noqa: F401
    Collider,
    DirichletNodes,
    DirichletPoints,
    ForcePatch,
    FrameStats,
    MPMSolver,
    ParticlePins,
    SimulationError,
    deform_covariances,
    mass_scale_for,
    material_mass_scales,
    polar_rotation,
    resolve_device,
    rotate_quaternions,
)
