"""Schema of the material oracle's answers (paper sec. 3.2): one material, an object's materials, an LLM answer.

Units are SI throughout: Pa, kg/m^3, Pa s; strains and Poisson's ratio are dimensionless ("1").

Conventions the simulator relies on
-----------------------------------
* ``squeeze_threshold`` is a compressive engineering strain at the finger contact (indentation depth divided by
  the object's local thickness along the squeeze direction): 0.15 means 15 %.  ``None`` means the object never
  ruptures; it then only shows its ``effect`` (rebound, dent, buckle).
* ``fluid`` materials carry ``youngs_modulus``/``poisson_ratio`` as the *equivalent isotropic pair* whose bulk
  modulus ``E / (3 (1 - 2 nu))`` is the liquid's bulk modulus (see :attr:`MaterialProperties.bulk_modulus`);
  the shear modulus that pair implies is not physical and a fluid model must ignore it (its shear stress comes
  from ``viscosity``).  Table fluids use ``nu = 0.49`` so that Lame's lambda is within 1.5 % of K as well.
* ``yield_stress`` is the uniaxial yield stress (von Mises: sqrt(3/2) |dev tau| <= yield_stress).  It is
  required for the plastic models ``stvk_hencky_von_mises`` and ``foam``; elastic entries leave it ``None``.
* ``core`` is the solid that fills the cavity and holds the shell up (fruit pulp, plush stuffing): it is part
  of the object's body whether or not the threshold is ever reached.  ``interior`` is what is *released* past
  the threshold (juice, cola, loose stuffing).  With a core, the released interior is made of core particles
  near the rupture (the pulp's cells burst into juice; stuffing tears loose), so the two must have the same
  density (mass is conserved).  Without a core (a sealed can of cola) the interior fills the cavity itself.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Optional

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator
from pydantic_core import PydanticCustomError

MODELS: tuple[str, ...] = ("fixed_corotated", "neo_hookean", "stvk_hencky_von_mises", "foam", "fluid")
PLASTIC_MODELS: tuple[str, ...] = ("stvk_hencky_von_mises", "foam")
EFFECTS: tuple[str, ...] = ("none", "rebound", "dent", "buckle", "juice", "cola_spray", "stuffing_spill")
SPILL_EFFECTS: tuple[str, ...] = ("juice", "cola_spray", "stuffing_spill")
BACKENDS: tuple[str, ...] = ("table", "llm", "explicit")
DIAMOND_YOUNGS_MODULUS = 1.2e12  # Pa, the stiffest solid (an E above it is a unit mistake)


class MaterialOracleError(ValueError):
    """The oracle cannot give valid materials; the one-line message names the field or input and the fix."""


def _fail(message: str) -> PydanticCustomError:
    # the template is "{m}" so that braces inside the message are never interpreted as placeholders
    return PydanticCustomError("material", "{m}", {"m": message})


def _finite(name: str, value: float, unit: str) -> None:
    if not math.isfinite(value):
        raise _fail(f"{name} {value} is not a finite number: give {name} in {unit}")


def _check_threshold(v: Optional[float]) -> Optional[float]:
    if v is not None and not (math.isfinite(v) and 0.0 < v < 1.0):
        raise _fail(f"squeeze_threshold {v:g} must be in (0, 1): it is the compressive engineering strain "
                    "at the finger contact where rupture starts (0.15 = 15 %), or null for never")
    return v


def _check_effect(v: Any) -> Any:
    if v not in EFFECTS:
        raise _fail(f"effect {v!r} is not a known effect: use one of {', '.join(EFFECTS)}")
    return v


class MaterialProperties(BaseModel):
    """One material of a squeezable object (SI units: Pa, kg/m^3, Pa s)."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)

    name: str = Field("", description="short material name, e.g. 'aluminium 3004-H19'")
    model: str = Field(
        description="constitutive model: fixed_corotated | neo_hookean (elastic), stvk_hencky_von_mises "
                    "(elastoplastic, von Mises), foam (viscoplastic/crushable), fluid (weakly compressible)",
        json_schema_extra={"enum": list(MODELS)})
    youngs_modulus: float = Field(description="Young's modulus E in Pa (fluids: 3 K (1 - 2 nu), K = bulk modulus)")
    poisson_ratio: float = Field(description="Poisson's ratio nu, dimensionless, 0 <= nu <= 0.49")
    density: float = Field(description="mass density in kg/m^3 (water = 1000)")
    yield_stress: Optional[float] = Field(
        None, description="uniaxial yield stress in Pa; required for stvk_hencky_von_mises and foam, "
                          "null for purely elastic materials")
    viscosity: Optional[float] = Field(None, description="dynamic viscosity in Pa s; required for fluid")
    hardening: Optional[float] = Field(None, description="linear hardening modulus in Pa (plastic models), "
                                                         "optional")
    source: str = Field(description="where the values come from: handbook, paper, or 'engineering choice'")
    note: str = Field("", description="caveats for the simulator (scaling, anisotropy, ...)")

    @field_validator("model", mode="before")
    @classmethod
    def _model_known(cls, v: Any) -> Any:
        if v not in MODELS:
            raise _fail(f"model {v!r} is not a known model: use one of {', '.join(MODELS)}")
        return v

    @field_validator("youngs_modulus")
    @classmethod
    def _e_positive(cls, v: float) -> float:
        _finite("youngs_modulus", v, "Pa")
        if v <= 0:
            raise _fail(f"youngs_modulus {v:g} must be > 0 Pa: give Young's modulus in pascals "
                        "(soft rubber ~1e6, aluminium 6.9e10)")
        if v > DIAMOND_YOUNGS_MODULUS:
            raise _fail(f"youngs_modulus {v:g} Pa exceeds diamond ({DIAMOND_YOUNGS_MODULUS:g} Pa): give Young's modulus in Pa")
        return v

    @field_validator("poisson_ratio")
    @classmethod
    def _nu_range(cls, v: float) -> float:
        _finite("poisson_ratio", v, "[0, 0.49]")
        if v >= 0.5:
            raise _fail(f"poisson_ratio {v:g} >= 0.5 makes the material incompressible (infinite lambda): "
                        "use <= 0.49")
        if v < 0:
            raise _fail(f"poisson_ratio {v:g} < 0 (auxetic) is not supported: use 0 <= poisson_ratio <= 0.49")
        return v

    @field_validator("density")
    @classmethod
    def _rho_range(cls, v: float) -> float:
        _finite("density", v, "kg/m^3")
        if v <= 0:
            raise _fail(f"density {v:g} must be > 0 kg/m^3")
        if v < 5:
            raise _fail(f"density {v:g} kg/m^3 is below 5 kg/m^3 (lighter than any foam): density is in "
                        "kg/m^3, not g/cm^3 (water = 1000)")
        if v > 25000:
            raise _fail(f"density {v:g} kg/m^3 exceeds osmium (22590 kg/m^3): give density in kg/m^3")
        return v

    @field_validator("yield_stress")
    @classmethod
    def _yield_positive(cls, v: Optional[float]) -> Optional[float]:
        if v is not None:
            _finite("yield_stress", v, "Pa")
            if v <= 0:
                raise _fail(f"yield_stress {v:g} must be > 0 Pa (or null for a purely elastic material)")
        return v

    @field_validator("viscosity")
    @classmethod
    def _viscosity_positive(cls, v: Optional[float]) -> Optional[float]:
        if v is not None:
            _finite("viscosity", v, "Pa s")
            if v < 0:
                raise _fail(f"viscosity {v:g} must be >= 0 Pa s (water = 1e-3)")
        return v

    @field_validator("hardening")
    @classmethod
    def _hardening_positive(cls, v: Optional[float]) -> Optional[float]:
        if v is not None:
            _finite("hardening", v, "Pa")
            if v < 0:
                raise _fail(f"hardening {v:g} must be >= 0 Pa (or null for perfect plasticity)")
        return v

    @field_validator("source")
    @classmethod
    def _source_given(cls, v: str) -> str:
        if not v.strip():
            raise _fail("source is empty: cite where the values come from (handbook, paper, or "
                        "'engineering choice')")
        return v

    @model_validator(mode="after")
    def _model_needs(self) -> "MaterialProperties":
        if self.model in PLASTIC_MODELS:
            if self.yield_stress is None:
                raise _fail(f"yield_stress is required for model {self.model!r} (plastic): give the uniaxial "
                            "yield stress in Pa or pick an elastic model (fixed_corotated, neo_hookean)")
            if self.yield_stress >= self.youngs_modulus:
                raise _fail(f"yield_stress {self.yield_stress:g} >= youngs_modulus {self.youngs_modulus:g} "
                            "means a yield strain above 100 %: check units (both in Pa)")
        if self.model == "fluid" and not self.viscosity:
            raise _fail("viscosity is required (> 0 Pa s) for model 'fluid': give the dynamic viscosity "
                        "(water = 1e-3 Pa s)")
        return self

    # derived quantities (not fields: they follow from E, nu, rho)
    @property
    def shear_modulus(self) -> float:
        """Lame's mu = E / (2 (1 + nu)) in Pa (not physical for fluids, see module docstring)."""
        return self.youngs_modulus / (2.0 * (1.0 + self.poisson_ratio))

    @property
    def lame_lambda(self) -> float:
        """Lame's lambda = E nu / ((1 + nu)(1 - 2 nu)) in Pa."""
        nu = self.poisson_ratio
        return self.youngs_modulus * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))

    @property
    def bulk_modulus(self) -> float:
        """K = E / (3 (1 - 2 nu)) in Pa."""
        return self.youngs_modulus / (3.0 * (1.0 - 2.0 * self.poisson_ratio))

    @property
    def wave_speed(self) -> float:
        """Fastest elastic wave speed in m/s: P-wave sqrt((lambda + 2 mu)/rho); fluids sqrt(K/rho)."""
        if self.model == "fluid":
            return math.sqrt(self.bulk_modulus / self.density)
        return math.sqrt((self.lame_lambda + 2.0 * self.shear_modulus) / self.density)


class ObjectMaterials(BaseModel):
    """Everything the simulator needs to know about what an object is made of."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)

    shell: MaterialProperties
    interior: Optional[MaterialProperties] = None
    core: Optional[MaterialProperties] = None  # solid filling that supports the shell (pulp, stuffing), see above
    squeeze_threshold: Optional[float] = None  # 1, compressive engineering strain at the finger contact
    threshold_source: str = ""  # where the threshold comes from (measurement, literature range, choice)
    effect: str = "none"
    matched_entry: str = ""
    backend: str = "table"
    notes: list[str] = Field(default_factory=list)  # provenance: overrides applied, interior dropped, ...

    @field_validator("squeeze_threshold")
    @classmethod
    def _threshold_range(cls, v: Optional[float]) -> Optional[float]:
        return _check_threshold(v)

    @field_validator("effect", mode="before")
    @classmethod
    def _effect_known(cls, v: Any) -> Any:
        return _check_effect(v)

    @field_validator("backend", mode="before")
    @classmethod
    def _backend_known(cls, v: Any) -> Any:
        if v not in BACKENDS:
            raise _fail(f"backend {v!r} is not one of {', '.join(BACKENDS)}")
        return v

    @model_validator(mode="after")
    def _core_matches_interior(self) -> "ObjectMaterials":
        if self.core is not None:
            if self.core.model == "fluid":
                raise _fail("core must be a solid (it holds the shell up): use interior for a liquid")
            if self.interior is None:
                raise _fail("core without an interior: a core is the solid the released interior is made of")
            if abs(self.core.density - self.interior.density) > 1e-9 * self.interior.density:
                raise _fail(f"core density {self.core.density:g} differs from the interior's "
                            f"{self.interior.density:g} kg/m^3: the released interior is converted from core "
                            "particles, so both need the same density")
        return self

    @model_validator(mode="after")
    def _spill_needs_threshold(self) -> "ObjectMaterials":
        if self.effect in SPILL_EFFECTS and self.squeeze_threshold is None:
            raise _fail(f"effect {self.effect!r} needs a squeeze_threshold (the strain where rupture starts): "
                        "give material.squeeze_threshold, e.g. 0.15")
        return self


class LLMAnswer(BaseModel):
    """Physical properties of one squeezable object (SI units); unknown keys are not allowed."""

    model_config = ConfigDict(extra="forbid", strict=True)

    shell: MaterialProperties = Field(description="material of the visible body / wall of the object")
    interior: Optional[MaterialProperties] = Field(
        None, description="material filling the object (juice, cola, stuffing ...), null when hollow/none")
    squeeze_threshold: Optional[float] = Field(
        None, description="compressive engineering strain (0..1) at the finger contact where rupture/overflow "
                          "starts; null if the object never ruptures when squeezed by hand")
    threshold_source: str = Field(description="where the threshold comes from (measurement, literature, "
                                              "engineering choice)")
    effect: str = Field(description="secondary effect: none | rebound | dent | buckle | juice | cola_spray | "
                                    "stuffing_spill", json_schema_extra={"enum": list(EFFECTS)})

    @field_validator("effect", mode="before")
    @classmethod
    def _effect_known(cls, v: Any) -> Any:
        return _check_effect(v)

    @field_validator("squeeze_threshold")
    @classmethod
    def _threshold_range(cls, v: Optional[float]) -> Optional[float]:
        return _check_threshold(v)


def one_line(exc: ValidationError, prefix: tuple[str, ...] = ()) -> str:
    """A pydantic ValidationError as one line: ``<prefix>.<path>.<message>; ...`` (input values are never echoed)."""
    parts = []
    for err in exc.errors(include_url=False, include_input=False):
        loc = list(prefix) + [str(x) for x in err["loc"]]
        msg = str(err["msg"])
        if err["type"] == "material":
            if loc and msg.startswith(loc[-1]):
                loc = loc[:-1]  # the message already starts with the field name
            parts.append(".".join(loc + [msg]) if loc else msg)
        else:
            parts.append(f"{'.'.join(loc) or '<root>'}: {msg}")
    return "; ".join(parts)


def validate_material(data: Mapping[str, Any]) -> MaterialProperties:
    """``MaterialProperties`` from a dict, raising :class:`MaterialOracleError` with a one-line message."""
    try:
        return MaterialProperties.model_validate(dict(data))
    except ValidationError as exc:
        raise MaterialOracleError(one_line(exc)) from None
