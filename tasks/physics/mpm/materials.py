"""Material descriptions for the MPM solver (SI units throughout).

A :class:`Material` names a constitutive model and its parameters.  The solver packs a list of materials
into a small parameter table (one row per material, see :func:`pack_table`) and every particle carries the
row index of its material, so a shell and an interior of different materials share one grid.

Models (the integer code is what the kernels branch on, as the Warp constants ``MODEL_*`` of ``constitutive.py``,
which also holds the formulas):

======  ==================  ===================================================================================
code    name                description
======  ==================  ===================================================================================
0       ``fixed_corotated`` hyperelastic, Psi = mu |F - R|^2 + lambda/2 (J - 1)^2 (Stomakhin et al. 2012)
1       ``neo_hookean``     compressible Neo-Hookean, Psi = mu/2 (tr F^T F - 3) - mu ln J + lambda/2 (ln J)^2
2       ``von_mises``       StVK-Hencky elasticity + von Mises plasticity on the Hencky strain (clay, metal,
                            paper), ``yield_stress`` = UNIAXIAL yield stress tau_y, optional linear
                            hardening ``hardening`` = H (tau_y(alpha) = tau_y + H alpha, alpha = equivalent
                            plastic strain)
3       ``foam``            viscoplastic foam (stuffing): StVK-Hencky + Perzyna-regularised von Mises
                            (relaxation time viscosity / (2 mu)) + a volumetric crush cap (compressive volumetric
                            Hencky strain beyond ``crush_strain`` becomes permanent compaction) and a dilation cap
                            (tensile volumetric strain beyond ``dilation_strain`` becomes permanent: it tears open)
4       ``fluid``           weakly compressible Tait fluid (juice, cola): p = K/gamma (J^-gamma - 1), plus
                            Newtonian viscosity 2 mu_v dev(sym grad v); F is reset to J^(1/3) I every step
======  ==================  ===================================================================================
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Optional, Sequence

import numpy as np

MODEL_CODES: dict[str, int] = {
    "fixed_corotated": 0,
    "neo_hookean": 1,
    "von_mises": 2,
    "foam": 3,
    "fluid": 4,
}
MODEL_ALIASES: dict[str, str] = {
    "elastic": "fixed_corotated",
    "jelly": "fixed_corotated",
    "corotated": "fixed_corotated",
    "neohookean": "neo_hookean",
    "stvk_hencky_von_mises": "von_mises",
    "hencky_von_mises": "von_mises",
    "plastic": "von_mises",
    "metal": "von_mises",
    "clay": "von_mises",
    "viscoplastic": "foam",
    "stuffing": "foam",
    "liquid": "fluid",
    "water": "fluid",
}
PLASTIC_MODELS = (MODEL_CODES["von_mises"], MODEL_CODES["foam"])
MEMBRANE_MODELS = ("fixed_corotated", "neo_hookean", "von_mises")  # the models held in plane stress on thin walls

# column layout of the packed material table (float32, one row per material)
COL_MU = 0
COL_LAMBDA = 1
COL_DENSITY = 2  # effective (mass-scaled) density, kg/m^3
COL_YIELD = 3  # uniaxial yield stress, Pa
COL_HARDENING = 4  # linear hardening modulus H, Pa
COL_VISCOSITY = 5  # Pa s
COL_BULK = 6  # bulk modulus K (fluid), Pa
COL_GAMMA = 7  # Tait exponent (fluid)
COL_CRUSH = 8  # foam volumetric crush strain (>= 0)
COL_PHYSICAL_DENSITY = 9  # physical (unscaled) density, kg/m^3: the weight m_phys g the particle feels
COL_DILATION = 10  # foam volumetric dilation (tear) strain (>= 0)
COL_DAMPING = 11  # local damping coefficient in [0, 1) (quasi-static damping of mass-scaled solids; 0 = none)
N_COLS = 12


class MaterialError(ValueError):
    """A material parameter is out of its physical range."""


@dataclass
class Material:
    """One material (SI units).

    Attributes:
        name: free label, used in error messages ("can_shell", "juice", ...).
        model: one of ``fixed_corotated``, ``neo_hookean``, ``von_mises``, ``foam``, ``fluid`` (aliases such as
            ``elastic``, ``metal``, ``clay``, ``stuffing``, ``water`` are accepted).
        youngs_modulus: E in Pa (> 0).  For ``fluid`` only used to derive the bulk modulus when
            ``bulk_modulus`` is not given.
        poisson_ratio: nu, 0 <= nu < 0.5.  nu = 0.5 is rejected (lambda would be infinite).
        density: rho in kg/m^3 (> 0).
        yield_stress: uniaxial yield stress tau_y in Pa (models ``von_mises`` and ``foam``); von Mises criterion
            sqrt(3/2) |dev tau| <= tau_y, so a bar in uniaxial tension/compression yields at |stress| = tau_y.
        hardening: linear isotropic hardening modulus H in Pa (tau_y grows by H per unit equivalent plastic
            strain); 0 = perfect plasticity.
        viscosity: dynamic viscosity in Pa s: Newtonian viscosity of ``fluid``; Perzyna viscosity of ``foam``
            (0 = rate independent); ignored by the other models.
        bulk_modulus: K in Pa for ``fluid`` (default: E / (3 (1 - 2 nu))).
        fluid_gamma: Tait exponent gamma for ``fluid`` (7 for water-like liquids, 1 gives p = K (1/J - 1)).
        crush_strain: ``foam`` only: compressive volumetric Hencky strain (>= 0) beyond which compression is
            permanent.  Use a large value (e.g. 10) to disable the cap.
        dilation_strain: ``foam`` only: tensile volumetric Hencky strain (>= 0) beyond which expansion is permanent
            (the material tears open and fragments instead of stretching elastically); 10 (default) = no cap.
        mass_scaled: whether selective mass scaling (``mpm.mass_scaling=selective``) multiplies this material's
            density (True: a solid that only deforms quasi-statically, e.g. a shell under the fingers) or leaves
            it physical (False: released or flying material, fluids).  None = every model but ``fluid``.  The
            other scaling modes ignore it.
        cohesion: Pa, a material of the released velocity field (``mass_scaled`` False under
            ``mpm.multi_field``) only: the tensile strength of its contact with the body.  Where the two fields
            separate at a node, the impulse that would stop the separation is applied up to cohesion x the node's
            share of the interface (from the released field's mass gradient) x dt, so a blob pulled off the body
            at more than this stress per unit contact area leaves and one pulled less stays; the tangential
            contact stays frictionless (:func:`tasks.physics.mpm.kernels.grid.k_field_contact`).  0 (default): the
            fields separate freely.  Torn-out stuffing: its fibres stay entangled with the stuffing it tore from.
        membrane: the material's particles are a wall thinner than the grid spacing, held in plane stress
            (``fixed_corotated``, ``neo_hookean``, and ``von_mises`` with its return mapping in plane stress; the
            solver's ``membrane_normals`` give each particle its rest normal, which von Mises then carries as the
            wall's current normal; every particle of the material needs one).  No stress acts across the wall, so
            its fastest wave is the in-plane one, sqrt(E / (rho (1 - nu^2))), which sets its stable step
            (:meth:`p_wave_speed`).
    """

    name: str = "material"
    model: str = "fixed_corotated"
    youngs_modulus: float = 1.0e5
    poisson_ratio: float = 0.3
    density: float = 1000.0
    yield_stress: float = 0.0
    hardening: float = 0.0
    viscosity: float = 0.0
    bulk_modulus: Optional[float] = None
    fluid_gamma: float = 7.0
    crush_strain: float = 0.05
    dilation_strain: float = 10.0
    mass_scaled: Optional[bool] = None
    cohesion: float = 0.0
    membrane: bool = False

    def __post_init__(self) -> None:
        self.model = canonical_model(self.model)
        self.validate()

    # ------------------------------------------------------------------ validation
    def validate(self) -> None:
        """Raise :class:`MaterialError` when a parameter is outside its physical range."""
        E, nu, rho = float(self.youngs_modulus), float(self.poisson_ratio), float(self.density)
        if not math.isfinite(E) or E <= 0.0:
            raise MaterialError(f"material '{self.name}': youngs_modulus must be > 0 Pa (got {E})")
        if not math.isfinite(nu) or nu < 0.0:
            raise MaterialError(f"material '{self.name}': poisson_ratio must be >= 0 (got {nu})")
        if nu >= 0.5:
            raise MaterialError(
                f"material '{self.name}': poisson_ratio {nu:g} makes lambda infinite; use <= 0.49"
            )
        if not math.isfinite(rho) or rho <= 0.0:
            raise MaterialError(f"material '{self.name}': density must be > 0 kg/m^3 (got {rho})")
        if self.model in ("von_mises", "foam") and not self.yield_stress > 0.0:
            raise MaterialError(
                f"material '{self.name}': model '{self.model}' needs yield_stress > 0 Pa (uniaxial yield stress)"
            )
        for attr in ("yield_stress", "hardening", "viscosity", "crush_strain", "dilation_strain", "cohesion"):
            val = float(getattr(self, attr))
            if not math.isfinite(val) or val < 0.0:
                raise MaterialError(f"material '{self.name}': {attr} must be >= 0 (got {val})")
        if self.cohesion > 0.0 and self.is_mass_scaled:
            raise MaterialError(f"material '{self.name}': cohesion is the strength of a released-field material's "
                                f"contact with the body; give it mass_scaled=False or cohesion 0")
        if self.bulk_modulus is not None and not self.bulk_modulus > 0.0:
            raise MaterialError(f"material '{self.name}': bulk_modulus must be > 0 Pa (got {self.bulk_modulus})")
        if self.membrane and self.model not in MEMBRANE_MODELS:
            raise MaterialError(f"material '{self.name}': a membrane must be one of {', '.join(MEMBRANE_MODELS)} "
                                f"(got '{self.model}')")
        if not self.fluid_gamma >= 1.0:
            raise MaterialError(f"material '{self.name}': fluid_gamma must be >= 1 (got {self.fluid_gamma})")

    # ------------------------------------------------------------------ derived quantities
    @property
    def code(self) -> int:
        return MODEL_CODES[self.model]

    @property
    def is_mass_scaled(self) -> bool:
        """Selective mass scaling applies to this material (see ``mass_scaled``)."""
        return self.model != "fluid" if self.mass_scaled is None else bool(self.mass_scaled)

    @property
    def is_plastic(self) -> bool:
        return self.code in PLASTIC_MODELS

    @property
    def mu(self) -> float:
        """Shear modulus (Lame mu) in Pa; 0 for a fluid."""
        if self.model == "fluid":
            return 0.0
        return self.youngs_modulus / (2.0 * (1.0 + self.poisson_ratio))

    @property
    def lam(self) -> float:
        """First Lame parameter lambda in Pa (0 for a fluid; the fluid uses :attr:`bulk`)."""
        if self.model == "fluid":
            return 0.0
        E, nu = self.youngs_modulus, self.poisson_ratio
        return E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))

    @property
    def bulk(self) -> float:
        """Bulk modulus K in Pa."""
        if self.bulk_modulus is not None:
            return float(self.bulk_modulus)
        return self.youngs_modulus / (3.0 * (1.0 - 2.0 * self.poisson_ratio))

    def p_wave_speed(self, stiffness_scale: float = 1.0, mass_scale: float = 1.0) -> float:
        """Dilatational wave speed in m/s.

        Solids: c_p = sqrt(E (1 - nu) / (rho (1 + nu) (1 - 2 nu))) = sqrt((lambda + 2 mu) / rho); a ``membrane``
        (plane stress): c_p = sqrt(E / (rho (1 - nu^2))), 3.6x slower at nu = 0.49, 1.7x at 0.45.
        Fluid: c = sqrt(K / rho) (Tait: dp/drho at rest).  ``stiffness_scale`` multiplies E (or K),
        ``mass_scale`` multiplies rho.
        """
        rho = self.density * mass_scale
        if self.model == "fluid":
            return math.sqrt(self.bulk * stiffness_scale / rho)
        E, nu = self.youngs_modulus * stiffness_scale, self.poisson_ratio
        if self.membrane:
            return math.sqrt(E / (rho * (1.0 - nu * nu)))
        return math.sqrt(E * (1.0 - nu) / (rho * (1.0 + nu) * (1.0 - 2.0 * nu)))

    def bar_wave_speed(self) -> float:
        """Slender-bar (1D) wave speed sqrt(E / rho) in m/s."""
        return math.sqrt(self.youngs_modulus / self.density)

    def scaled(self, stiffness_scale: float = 1.0) -> "Material":
        """A copy with E (and an explicit K) multiplied by ``stiffness_scale``; yield stress is unchanged."""
        return replace(
            self,
            youngs_modulus=self.youngs_modulus * stiffness_scale,
            bulk_modulus=None if self.bulk_modulus is None else self.bulk_modulus * stiffness_scale,
        )


def canonical_model(model: str | int) -> str:
    """Normalise a model name or code (``"elastic"`` -> ``"fixed_corotated"``, ``2`` -> ``"von_mises"``)."""
    if isinstance(model, (int, np.integer)):
        for name, code in MODEL_CODES.items():
            if code == int(model):
                return name
        raise MaterialError(f"unknown material model code {model}; known: {MODEL_CODES}")
    key = str(model).strip().lower().replace("-", "_").replace(" ", "_")
    key = MODEL_ALIASES.get(key, key)
    if key not in MODEL_CODES:
        raise MaterialError(
            f"unknown material model '{model}'; known: {sorted(MODEL_CODES)} (aliases {sorted(MODEL_ALIASES)})"
        )
    return key


def pack_table(materials: Sequence[Material], stiffness_scale: float = 1.0,
               mass_scale: float | Sequence[float] = 1.0,
               damping: float | Sequence[float] = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Pack materials into ``(models int32 [M], params float32 [M, N_COLS])`` for the kernels.

    ``stiffness_scale`` multiplies E (hence mu, lambda) and K; ``mass_scale`` (one factor, or one per material)
    multiplies the density of column ``COL_DENSITY`` (the inertia); ``COL_PHYSICAL_DENSITY`` keeps the physical
    density (the weight).  Yield stress and hardening are not scaled (stiffness scaling of a plastic material
    changes its yield strain).  ``damping`` (one coefficient, or one per material) fills ``COL_DAMPING``.
    """
    if len(materials) == 0:
        raise MaterialError("at least one material is needed")
    scales = np.broadcast_to(np.asarray(mass_scale, np.float64), (len(materials),))
    damp = np.broadcast_to(np.asarray(damping, np.float64), (len(materials),))
    models = np.zeros(len(materials), dtype=np.int32)
    params = np.zeros((len(materials), N_COLS), dtype=np.float32)
    for i, (m, s) in enumerate(zip(materials, scales.tolist())):
        m.validate()
        models[i] = m.code
        params[i, COL_MU] = m.mu * stiffness_scale
        params[i, COL_LAMBDA] = m.lam * stiffness_scale
        params[i, COL_DENSITY] = m.density * s
        params[i, COL_PHYSICAL_DENSITY] = m.density
        params[i, COL_YIELD] = m.yield_stress
        params[i, COL_HARDENING] = m.hardening
        params[i, COL_VISCOSITY] = m.viscosity
        params[i, COL_BULK] = m.bulk * stiffness_scale
        params[i, COL_GAMMA] = m.fluid_gamma
        params[i, COL_CRUSH] = m.crush_strain
        params[i, COL_DILATION] = m.dilation_strain
        params[i, COL_DAMPING] = damp[i]
    return models, params


def material_from_dict(d: dict) -> Material:
    """Build a :class:`Material` from a plain mapping (unknown keys are an error)."""
    known = set(Material.__dataclass_fields__)
    unknown = set(d) - known
    if unknown:
        raise MaterialError(f"unknown material keys {sorted(unknown)}; known: {sorted(known)}")
    return Material(**d)
