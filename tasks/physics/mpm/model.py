"""The solver's material model: the packed material table on the device (per-material mass scales, wave speeds,
where gravity acts, the stable step of explicit viscosity), the materials present, and the velocity field of
each material (the released field of ``mpm.multi_field``).
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Optional

import numpy as np
import warp as wp

from .materials import MODEL_CODES, Material, pack_table

if TYPE_CHECKING:
    from .solver import MPMSolver


FIXED_COROTATED = MODEL_CODES["fixed_corotated"]
VON_MISES = MODEL_CODES["von_mises"]


def resolve_device(device: Optional[str]) -> str:
    """``auto`` -> ``cuda:0`` when a CUDA device is present, else ``cpu``."""
    if device is None or device == "auto":
        return "cuda:0" if wp.get_cuda_device_count() > 0 else "cpu"
    return device


def present_materials(solver: MPMSolver) -> list[Material]:
    """The materials that particles have now."""
    return [solver.materials[i] for i in solver._present]


def upload_materials(solver: MPMSolver) -> None:
    """Material table with the per-material mass scales, wave speeds, and where gravity acts: uniform scale s
    among the materials present -> the grid adds g / s (``solver.gravity``); mixed -> the P2G adds dt m_phys g."""
    models, params = pack_table(solver.materials, solver.stiffness_scale, solver.material_mass_scale, solver._damping)
    solver._mat_params = params
    solver.mat_model.assign(models)
    solver.mat_par.assign(params)
    present = solver._present
    solver.wave_speeds = {solver.materials[i].name: solver.materials[i].p_wave_speed(
        solver.stiffness_scale, float(solver.material_mass_scale[i])) for i in present}  # m/s
    solver.c_max = max(solver.wave_speeds.values())
    solver.gravity = [g / solver.mass_scale for g in solver.cfg.gravity]
    scales = {float(solver.material_mass_scale[i]) for i in present}
    solver._weight_in_p2g = len(scales) > 1
    uniform = max(scales)
    solver._grid_gravity = [0.0, 0.0, 0.0] if solver._weight_in_p2g else [g / uniform for g in solver.cfg.gravity]
    solver._cmds = None  # the recorded launches hold the gravity
    solver.dt_visc = math.inf
    for i in present:
        m = solver.materials[i]
        if m.model == "fluid" and m.viscosity > 0:
            rho = m.density * float(solver.material_mass_scale[i])
            solver.dt_visc = min(solver.dt_visc, rho * solver.dx ** 2 / (6.0 * m.viscosity))


def released_field_materials(solver: MPMSolver) -> np.ndarray:
    """(material,) bool: the materials of the released velocity field (``mpm.multi_field`` under
    ``mpm.mass_scaling=selective``): those that keep their physical inertia while the body is scaled
    (``Material.is_mass_scaled`` False: released material, fluids).  Under the other modes every material has
    the same scale and one field is kept."""
    on = solver.cfg.multi_field and solver.cfg.mass_scaling == "selective"
    return np.array([on and not m.is_mass_scaled for m in solver.materials])


def update_fields(solver: MPMSolver) -> None:
    """Velocity field of each material (kernels: ``MaterialTable.field``).  Two fields only while both the body
    (field 0) and the released field (field 1) have particles: otherwise everything is field 0 and the second
    grid is neither allocated nor launched (the single-field path, unchanged).  The second pair of grid buffers
    is allocated (zeroed) when the second field first appears."""
    released = released_field_materials(solver)
    present = np.zeros(len(solver.materials), bool)
    present[solver._present] = True
    two = bool((released & present).any() and (~released & present).any())
    field = (released & two).astype(np.int32)
    # N/kg: the cohesion of the released field's contact with the body (kernels.k_field_contact), the largest
    # Material.cohesion / (2 rho dx) of its materials present
    cohesion = max([m.cohesion / (2.0 * m.density * solver.dx)
                    for m, on in zip(solver.materials, released & present & two) if on], default=0.0)
    if cohesion != solver.field_cohesion:
        solver._cmds = None  # the recorded launches hold the grid conditions
    solver.field_cohesion = cohesion
    solver.mat_field.assign(field)
    if two and solver._field2[id(solver.grid_a)].shape != solver.grid_a.shape:
        solver._field2 = {id(g): wp.zeros(solver.dims, dtype=wp.vec4, device=solver.device)
                          for g in (solver.grid_a, solver.grid_b)}
    if two != solver.two_fields:
        solver._cmds = None  # the recorded launches hold the grid buffers
        for g in solver._field2.values():
            g.zero_()
    solver.two_fields = two
