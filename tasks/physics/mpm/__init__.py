"""MLS-MPM physics core (NVIDIA Warp): materials, constitutive models, kernels and the solver driver."""
from .diagnostics import FrameStats, SimulationError  # noqa: F401
from .inputs import Collider, DirichletNodes, DirichletPoints, ForcePatch, ParticlePins  # noqa: F401
from .mass_scaling import mass_scale_for, material_mass_scales  # noqa: F401
from .materials import MODEL_CODES, Material, MaterialError, canonical_model, material_from_dict  # noqa: F401
from .model import resolve_device  # noqa: F401
from .solver import MPMSolver  # noqa: F401
from .tracers import deform_covariances, polar_rotation, rotate_quaternions  # noqa: F401
