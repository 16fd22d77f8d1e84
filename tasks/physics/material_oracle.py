"""Material oracle: an object's text description -> physical properties for the MPM simulation.

Paper, sec. 3.2 ("Squeezing-Driven Deformation"): before the MPM simulation an LLM (GPT-5) infers the object's
material type, Young's modulus, Poisson's ratio and yield strength, and a *squeezing threshold*: when the
deformation exceeds it, objects with suitable materials show secondary effects (rupture, overflow); below it
they only deform and e.g. rebound on release.  Interior particles (juice, cola, stuffing) get their own
material on the same MPM grid.

This module gives that step two backends behind one pure function, :func:`material_oracle`:

* ``table`` (default, offline, deterministic): :data:`TABLE`, a curated list of real material properties, each
  with a ``source`` string saying where the numbers come from and how sure they are.  A description (+ the
  object's name) is matched to an entry by keyword scores.
* ``llm``: any OpenAI-compatible ``POST {llm_url}/chat/completions`` endpoint.  The answer must be JSON that
  validates against :class:`LLMAnswer`; answers are cached on disk as JSON.  The API key comes from the
  environment variable named by ``cfg.api_key_env`` and is never logged, cached or put in an error message.

Explicit values in the object's ``material`` overrides always win and the merged result is validated again.

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

import hashlib
import json
import logging
import math
import os
import re
import time
import uuid
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import httpx
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator
from pydantic_core import PydanticCustomError

from tasks.core.step import artifact_step

log = logging.getLogger(__name__)

MODELS: tuple[str, ...] = ("fixed_corotated", "neo_hookean", "stvk_hencky_von_mises", "foam", "fluid")
ELASTIC_MODELS: tuple[str, ...] = ("fixed_corotated", "neo_hookean")
PLASTIC_MODELS: tuple[str, ...] = ("stvk_hencky_von_mises", "foam")
EFFECTS: tuple[str, ...] = ("none", "rebound", "dent", "buckle", "juice", "cola_spray", "stuffing_spill")
SPILL_EFFECTS: tuple[str, ...] = ("juice", "cola_spray", "stuffing_spill")
BACKENDS: tuple[str, ...] = ("table", "llm", "explicit")
OVERRIDE_KEYS: tuple[str, ...] = (
    "model", "youngs_modulus", "poisson_ratio", "density", "yield_stress", "squeeze_threshold")
SHELL_OVERRIDE_KEYS: tuple[str, ...] = OVERRIDE_KEYS[:-1]
# ``interior`` strings that mean "nothing simulated inside" (a hollow object's air is not an MPM material)
NO_INTERIOR: tuple[str, ...] = ("air", "none", "null", "empty", "hollow", "nothing", "gas")

PROMPT_VERSION = "virsqueezer-material-oracle-v1"
MAX_RESPONSE_BYTES = 2_000_000
WATER_BULK_MODULUS = 2.2e9  # Pa, water at 20 C (CRC Handbook of Chemistry and Physics)
FLUID_NU = 0.49  # Poisson's ratio of the equivalent elastic pair of table fluids (see module docstring)


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


# ----------------------------------------------------------------------------------------------- schema
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
        if v > 1.2e12:
            raise _fail(f"youngs_modulus {v:g} Pa exceeds diamond (1.2e12 Pa): give Young's modulus in Pa")
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


def one_line(exc: ValidationError) -> str:
    """A pydantic ValidationError as one line: ``<path>.<message>; ...`` (input values are never echoed)."""
    parts = []
    for err in exc.errors(include_url=False, include_input=False):
        loc = [str(x) for x in err["loc"]]
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


# ----------------------------------------------------------------------------------------------- table
@dataclass(frozen=True)
class TableEntry:
    """One object kind of the offline table: its shell, default interior, threshold and effect."""

    key: str
    title: str
    keywords: tuple[tuple[str, float], ...]  # (phrase, weight); a phrase counts once
    shell: MaterialProperties
    interior: Optional[str]  # key into INTERIORS, or None for hollow/solid objects
    squeeze_threshold: Optional[float]
    threshold_source: str
    effect: str


@dataclass(frozen=True)
class InteriorEntry:
    """An interior material; ``core`` is the solid tissue that holds it inside the body (see the module doc)."""

    key: str
    keywords: tuple[str, ...]
    material: MaterialProperties
    core: Optional[MaterialProperties] = None


def _fluid(name: str, density: float, viscosity: float, source: str, note: str = "",
           bulk_modulus: float = WATER_BULK_MODULUS) -> MaterialProperties:
    """A weakly compressible liquid: E, nu is the equivalent pair with E / (3 (1 - 2 nu)) = K."""
    return MaterialProperties(
        name=name, model="fluid", youngs_modulus=3.0 * bulk_modulus * (1.0 - 2.0 * FLUID_NU),
        poisson_ratio=FLUID_NU, density=density, viscosity=viscosity, source=source,
        note=(f"fluid: youngs_modulus/poisson_ratio encode the physical bulk modulus K = {bulk_modulus:.3g} Pa "
              "(speed of sound ~1.5 km/s); a weakly compressible MPM fluid usually scales K down (keep the "
              "flow Mach number < ~0.1) and must report the factor; shear stress comes from viscosity only. "
              + note).strip())


# the stuffing both holds a plush toy up (core) and is what spills from a torn seam (interior)
_FIBREFILL = MaterialProperties(
    name="polyester fibrefill stuffing", model="foam", youngs_modulus=5e3, poisson_ratio=0.15,
    density=25.0, yield_stress=1e3,
    source="engineering estimate: hollow PET staple fibre (fibre density 1.38 g/cm^3) packed at ~1.5-2.5 "
           "vol% in stuffed toys -> ~20-35 kg/m^3; the effective small-strain compressive modulus of such "
           "loose fibre assemblies is of order 1-10 kPa and stiffens strongly as the batting densifies "
           "(van Wyk's fibre-mass compression law, 1946); 5 kPa mid choice; yield 1 kPa and nu 0.15 (fibre "
           "batting barely expands sideways) are engineering choices, not measurements",
    note="Foam-like effective continuum; real fibre mass has no tensile strength and a strongly "
         "nonlinear compression curve.")
# what spills from a torn seam: loose tufts of the same fibre, cohesionless (no tension, no shear stiffness)
_LOOSE_FIBREFILL = MaterialProperties(
    name="loose polyester fibrefill (torn out)", model="fluid",
    youngs_modulus=3.0 * 5e3 * (1.0 - 2.0 * FLUID_NU), poisson_ratio=FLUID_NU, density=25.0, viscosity=1.0,
    source="the stuffing above once a seam is open: same density (25 kg/m^3); a loose fibre mass carries no "
           "tension, so it is modelled as a cohesionless, weakly compressible continuum (the model 'fluid': "
           "no tension, shear stress from viscosity only) with the batting's ~5 kPa compressive modulus as its "
           "bulk modulus; viscosity 1 Pa s is an engineering choice (it only damps the tufts' relative motion), "
           "not a measurement",
    note="Not a liquid: 'fluid' is the solver's only cohesionless model. The simulator sets its own bulk "
         "modulus with the mass scale, as for juice.")

_WATER_K_SRC = "bulk modulus of water 2.2 GPa at 20 C (CRC Handbook of Chemistry and Physics)"

INTERIORS: dict[str, InteriorEntry] = {e.key: e for e in (
    InteriorEntry("cola", ("cola", "coke", "soda", "carbonated", "fizzy", "soft drink", "pop", "drink",
                           "beverage"), _fluid(
        "regular cola", 1040.0, 1.3e-3,
        "regular cola carries ~10.6 g sugar per 100 mL -> density ~1.04 g/cm^3; viscosity taken as that of a "
        "~10 wt% aqueous sucrose solution at 20 C, ~1.3 mPa s (CRC Handbook, concentrative properties of "
        "aqueous sucrose); " + _WATER_K_SRC,
        note="A sealed can holds ~2-3.5 bar gauge of CO2 that drives the spray; that overpressure is not part "
             "of this material.")),
    InteriorEntry("tomato_juice", ("juice", "pulp", "tomato", "locular", "gel", "seed", "flesh", "juicy"), _fluid(
        "tomato juice / locular pulp", 1020.0, 5e-3,
        "tomato juice at ~5 Brix: density ~1.02 g/cm^3 (sugar-solution tables); serum (juice without insoluble "
        "solids) viscosity ~1-2 mPa s while the locular gel with seeds is shear-thinning and far more viscous; "
        "5 mPa s is an engineering choice inside the 1-10 mPa s range; " + _WATER_K_SRC),
        core=MaterialProperties(
            name="tomato flesh: inner pericarp, locular gel and columella (effective)", model="neo_hookean",
            youngs_modulus=0.1e6, poisson_ratio=0.45, density=1020.0,
            source="tomato pericarp flesh modulus of order 0.1-0.5 MPa (orders of magnitude of postharvest "
                   "tissue tests, e.g. Li et al. 2012, J. Food Eng. 111:82-91 - not verified against their "
                   "tables); the locular gel is far softer, so the low end 0.1 MPa is used for the whole cavity; "
                   "nu 0.45 for turgid, juice-filled tissue (assumed); density set equal to the juice's 1020 "
                   "kg/m^3 (whole tomatoes ~0.95-1.05 g/cm^3) so that bursting cells conserve mass",
            note="Solid flesh that holds the skin up; past the threshold the flesh at the rupture becomes "
                 "juice. Compressible neo-Hookean, a common hyperelastic model of soft fruit tissue.")),
    InteriorEntry("orange_juice", ("juice", "pulp", "orange", "segment", "citrus", "juicy", "flesh"), _fluid(
        "orange juice", 1045.0, 2e-3,
        "orange juice at ~11-12 Brix: density ~1.04-1.05 g/cm^3 (sugar-solution tables); pulp-free juice "
        "~1.5-3 mPa s at 20 C, pulp raises it; 2 mPa s chosen; " + _WATER_K_SRC),
        core=MaterialProperties(
            name="orange segments: juice vesicles in segment membranes (effective)", model="neo_hookean",
            youngs_modulus=0.1e6, poisson_ratio=0.45, density=1045.0,
            source="engineering estimate: citrus segments are a soft, juice-filled tissue, much softer than the "
                   "peel (peel modulus of order 1-3 MPa, Singh & Reddy 2006, J. Food Eng. 73:112-120); soft "
                   "fruit flesh moduli start at ~0.1 MPa (tomato pericarp, see the tomato entry), 0.1 MPa chosen, "
                   "not measured; nu 0.45 for juice-filled vesicles (assumed); density set equal to the juice's "
                   "1045 kg/m^3 (whole-orange density 1.03 g/cm^3, Sharifi et al. 2007, Int. Agrophys. "
                   "21:391-397) so that bursting vesicles conserve mass",
            note="Solid flesh that holds the peel up; past the threshold the flesh at the rupture becomes "
                 "juice. Compressible neo-Hookean, a common hyperelastic model of soft fruit tissue.")),
    InteriorEntry("water", ("water", "liquid"), _fluid(
        "water", 998.0, 1.0e-3,
        "water at 20 C: density 998 kg/m^3, viscosity 1.0 mPa s, " + _WATER_K_SRC)),
    InteriorEntry("polyester_fibrefill", ("stuffing", "fibrefill", "polyester", "filling", "fluff", "cotton",
                                          "wadding", "batting"), _LOOSE_FIBREFILL, core=_FIBREFILL),
)}

_GENT_SRC = "E from Gent's Shore-A hardness relation (A. N. Gent 1958, Trans. IRI 34:46)"
_RUBBER_NU = ("rubbery polymers are nearly incompressible (bulk modulus ~2 GPa, nu ~0.4995); nu capped at the "
              "validator limit 0.49")
_RUBBER_NOTE = ("nu = 0.49 makes the P-wave ~2x faster than nu = 0.45; a simulator that lowers nu for speed "
                "must report it.")

TABLE: tuple[TableEntry, ...] = (
    TableEntry(
        key="aluminium_can", title="aluminium beverage can (3004-H19 body) filled with cola",
        keywords=(("can", 2.5), ("aluminium", 3), ("beverage", 2), ("soda", 2), ("cola", 2), ("coke", 2),
                  ("carbonated", 1), ("drink", 1), ("fizzy", 1), ("metal", 1), ("tin can", 1)),
        shell=MaterialProperties(
            name="aluminium alloy 3004-H19 (can body stock)", model="stvk_hencky_von_mises",
            youngs_modulus=69.0e9, poisson_ratio=0.33, density=2720.0, yield_stress=285e6, hardening=0.5e9,
            source="aluminium 3004-H19 typical values: E 69 GPa, nu 0.33, density 2.72 g/cm^3, yield 285 MPa, "
                   "UTS 295 MPa (ASM Handbook Vol. 2, 1990; Aluminum Association, Aluminum Standards and "
                   "Data); hardening = (UTS - yield) / ~2 % elongation = 0.5 GPa, a rough estimate",
            note="Real wall ~0.1 mm thick. Explicit MPM at 69 GPa needs ~1e7 steps per simulated second at "
                 "mm grids; the simulator may scale stiffness or mass and must report it."),
        interior="cola", squeeze_threshold=0.25, effect="cola_spray",
        threshold_source="engineering choice: no measured 'hand-squeeze rupture strain' of a sealed can "
                         "exists; the 0.1 mm wall creases well before this, and at 25 % lateral crush strain "
                         "a fold is assumed to split and release the pressurised cola as a spray"),
    TableEntry(
        key="plush_toy", title="plush toy: polyester plush fabric shell with polyester fibrefill stuffing",
        keywords=(("plush", 3), ("stuffed", 3), ("teddy", 3), ("stuffing", 2), ("fibrefill", 2),
                  ("soft toy", 2), ("fabric", 2), ("polyester", 1), ("toy", 1), ("fleece", 1), ("bear", 1),
                  ("cuddly", 1)),
        shell=MaterialProperties(
            name="polyester plush fabric", model="fixed_corotated", youngs_modulus=0.3e6,
            poisson_ratio=0.3, density=300.0,
            source="engineering estimate: polyester plush fabric of areal density ~250-350 g/m^2 treated as a "
                   "~1 mm continuum -> ~300 kg/m^3; knitted pile fabrics have a small-strain tensile stiffness "
                   "of order 1e2-1e3 N/m, i.e. E ~0.1-1 MPa over 1 mm (woven fabrics are ~10x stiffer along "
                   "the yarns); 0.3 MPa and nu 0.3 are choices, not measured for a specific toy",
            note="A fabric has almost no bending or compressive stiffness; an isotropic solid shell "
                 "over-estimates both, so the low end of the range is used."),
        interior="polyester_fibrefill", squeeze_threshold=0.15, effect="stuffing_spill",
        threshold_source="engineering choice: a sewn plush toy does not burst under light hand squeezing; "
                         "a seam is assumed to open at 15 % compression under the fingertips (strain = mean "
                         "inward displacement under the fingertip / the toy's half-width: ~11 mm over the 72 mm "
                         "half-width, a firm squeeze pushing ~25 mm in at the fingertip centre; the earlier 30 % "
                         "needed the fingers pushed ~5 cm into the toy)"),
    TableEntry(
        key="rubber_duck", title="hollow bath duck of plasticised PVC vinyl",
        keywords=(("duck", 3), ("rubber", 2), ("vinyl", 2), ("pvc", 2), ("bath toy", 1), ("bath", 1),
                  ("squeaky", 1), ("squeak", 1)),
        shell=MaterialProperties(
            name="plasticised PVC (flexible vinyl), ~Shore A 75", model="neo_hookean", youngs_modulus=7.0e6,
            poisson_ratio=0.49, density=1300.0,
            source=f"flexible PVC of bath toys, hardness ~Shore A 70-80: {_GENT_SRC} = 5.5-9.4 MPa, 7.0 MPa "
                   "at Shore A 75; density 1.2-1.4 g/cm^3 (polymer handbooks, e.g. Mark (ed.), Physical "
                   f"Properties of Polymers Handbook); {_RUBBER_NU}; the toy's hardness itself is assumed, "
                   "not measured",
            note=_RUBBER_NOTE),
        interior=None, squeeze_threshold=None, effect="rebound",
        threshold_source="elastic hollow shell: no rupture under hand squeezing; rebounds on release"),
    TableEntry(
        key="modelling_clay", title="soft oil-based modelling clay / plasticine",
        keywords=(("clay", 3), ("plasticine", 3), ("modelling clay", 2), ("modelling", 1), ("putty", 2),
                  ("play doh", 2), ("playdoh", 2), ("dough", 1)),
        shell=MaterialProperties(
            name="soft modelling clay (plasticine)", model="stvk_hencky_von_mises", youngs_modulus=4.0e6,
            poisson_ratio=0.45, density=1700.0, yield_stress=4e4,
            source="oil/wax-based modelling clay filled with chalk/clay: density 1.6-1.8 g/cm^3; small-strain "
                   "modulus of order 0.1-1 MPa and flow stress of order 10-100 kPa at room temperature and hand "
                   "strain rates (plasticine compression tests, e.g. Green, 'The behaviour of plasticine when "
                   "permanently deformed', and analogue-modelling rheology, Zulauf & Zulauf 2004, J. Struct. "
                   "Geol. 26:725); yield 40 kPa is a choice inside that range for a SOFT clay, not verified against "
                   "those papers' tables; E 4 MPa is an engineering choice that makes the yield strain "
                   "tau_y/E = 1 %: plasticine flows almost rigid-plastically and keeps nearly all of a dent (with "
                   "E 0.5 MPa the 8 % yield strain made a hand squeeze mostly spring back, which plasticine does "
                   "not do); nu 0.45: nearly incompressible paste (assumed)",
            note="Real plasticine is strain-rate and temperature sensitive (viscoplastic)."),
        interior=None, squeeze_threshold=None, effect="dent",
        threshold_source="perfectly plastic paste: dents permanently, no rupture or overflow"),
    TableEntry(
        key="tomato", title="ripe tomato: thin skin + pericarp shell, juicy locular pulp",
        keywords=(("tomato", 4), ("thin skin", 1), ("juicy", 1), ("juice", 1), ("pulp", 1), ("ripe", 0.5),
                  ("fruit", 0.5), ("vegetable", 0.5)),
        shell=MaterialProperties(
            name="tomato skin + outer pericarp (effective)", model="fixed_corotated", youngs_modulus=2.0e6,
            poisson_ratio=0.45, density=1000.0,
            source="tomato skin (exocarp) tensile modulus is of order a few MPa and pericarp flesh ~0.1-0.5 MPa "
                   "(orders of magnitude of postharvest tissue tests, e.g. Li et al. 2012, J. Food Eng. "
                   "111:82-91; Bargel & Neinhuis 2005, J. Exp. Bot. 56:1049 - not verified against their "
                   "tables); 2 MPa is an engineering choice for a thin (~1 mm) skin + outer-pericarp shell; "
                   "fruit density ~0.95-1.05 g/cm^3; nu 0.45 for turgid tissue (assumed)",
            note="Real tomato tissue is viscoelastic and bruises (plastic) before it ruptures; a real pericarp "
                 "wall is 5-8 mm thick, so a 1 mm shell around a liquid interior is softer than a real fruit."),
        interior="tomato_juice", squeeze_threshold=0.15, effect="juice",
        threshold_source="postharvest compression tests of whole ripe tomatoes put rupture at roughly 10-20 % "
                         "deformation of the diameter (cultivar, ripeness and size dependent); 0.15 is the "
                         "mid-range choice, not verified against a specific paper's table"),
    TableEntry(
        key="orange", title="orange: thick peel (flavedo + albedo) around juicy segments",
        keywords=(("orange", 3), ("citrus", 3), ("mandarin", 3), ("tangerine", 3), ("clementine", 3),
                  ("navel", 2), ("peel", 1.5), ("segment", 1.5), ("juicy", 1), ("juice", 1), ("rind", 1),
                  ("fruit", 0.5)),
        shell=MaterialProperties(
            name="orange peel (flavedo + albedo)", model="fixed_corotated", youngs_modulus=2.0e6,
            poisson_ratio=0.05, density=850.0,
            source="orange peel modulus of order 1-3 MPa (Singh & Reddy 2006, J. Food Eng. 73:112-120; "
                   "Jentzsch et al. 2022, Front. Mater. 9:979151); Jentzsch et al. report Poisson ratios close "
                   "to zero or slightly negative for compressed citrus peels; the air-filled albedo makes the "
                   "peel lighter than water (850 kg/m^3 is an estimate); E 2 MPa is a mid-range choice",
            note="Peel 3-6 mm thick, foam-like and energy absorbing."),
        interior="orange_juice", squeeze_threshold=0.2, effect="juice",
        threshold_source="engineering choice: the thick, energy-absorbing peel is assumed to delay rupture "
                         "compared with a tomato (0.15), so 0.2 (7.5 mm indentation under the fingertips of a "
                         "75 mm orange); no measured value for hand squeezing"),
    TableEntry(
        key="rubber_ball", title="hollow natural-rubber ball",
        keywords=(("ball", 3), ("rubber", 2), ("bouncy", 1), ("bouncing", 1), ("latex", 1),
                  ("natural rubber", 1)),
        shell=MaterialProperties(
            name="vulcanised natural-rubber compound, ~Shore A 50", model="neo_hookean", youngs_modulus=2.5e6,
            poisson_ratio=0.49, density=1150.0,
            source=f"filled natural-rubber compound, ~Shore A 50: {_GENT_SRC} = 2.5 MPa (Shore A 40-60 gives "
                   "1.6-3.6 MPa); filled NR density 1.1-1.2 g/cm^3 (unfilled gum 0.93); "
                   f"{_RUBBER_NU}; hardness assumed, not measured",
            note=_RUBBER_NOTE),
        interior=None, squeeze_threshold=None, effect="rebound",
        threshold_source="elastic hollow shell: no rupture under hand squeezing; rebounds on release"),
    TableEntry(
        key="paper_cup", title="paper cup of thin paperboard (cup stock)",
        keywords=(("cup", 3), ("paper", 3), ("paperboard", 3), ("cardboard", 2), ("carton", 1),
                  ("disposable", 1)),
        shell=MaterialProperties(
            name="paperboard (solid bleached board cup stock)", model="stvk_hencky_von_mises",
            youngs_modulus=4.0e9, poisson_ratio=0.3, density=750.0, yield_stress=25e6,
            source="paperboard: in-plane E ~5-8 GPa machine direction and ~2-4 GPa cross direction, in-plane "
                   "Poisson ratio ~0.2-0.4, density 650-850 kg/m^3, elastic limit ~20-40 MPa (typical ranges, "
                   "e.g. Niskanen (ed.), Mechanics of Paper Products, De Gruyter 2012); isotropic mid values "
                   "used",
            note="Paperboard is orthotropic; its out-of-plane modulus (tens of MPa) and the PE coating are not "
                 "represented. Explicit MPM at 4 GPa needs stiffness or mass scaling."),
        interior=None, squeeze_threshold=None, effect="buckle",
        threshold_source="thin elastoplastic wall: buckles and creases permanently; nothing inside to spill"),
    TableEntry(
        key="silicone_toy", title="solid soft silicone-rubber squeeze toy",
        keywords=(("silicone", 4), ("squishy", 1), ("rubber", 1)),
        shell=MaterialProperties(
            name="platinum-cure silicone rubber, ~Shore A 25", model="neo_hookean", youngs_modulus=0.9e6,
            poisson_ratio=0.49, density=1100.0,
            source=f"soft silicone rubber ~Shore A 25: {_GENT_SRC} = 0.9 MPa; density 1.07-1.2 g/cm^3 "
                   f"(supplier data sheets); {_RUBBER_NU}",
            note=_RUBBER_NOTE),
        interior=None, squeeze_threshold=None, effect="rebound",
        threshold_source="elastic solid: no rupture under hand squeezing; rebounds on release"),
    TableEntry(
        key="foam_sponge", title="flexible polyurethane foam (sponge, stress ball)",
        keywords=(("foam", 3), ("sponge", 3), ("polyurethane", 3), ("stress ball", 4), ("memory foam", 2)),
        shell=MaterialProperties(
            name="flexible open-cell polyurethane foam, ~30 kg/m^3", model="foam", youngs_modulus=50e3,
            poisson_ratio=0.3, density=30.0, yield_stress=5e3,
            source="flexible PU foam of density ~25-40 kg/m^3: compressive modulus ~10-100 kPa and collapse "
                   "(plateau) stress ~2-10 kPa; open-cell foams have nu ~1/3 (Gibson & Ashby, Cellular Solids, "
                   "2nd ed., CUP 1997); mid values chosen"),
        interior=None, squeeze_threshold=None, effect="rebound",
        threshold_source="open-cell foam recovers after release; no rupture under hand squeezing"),
)
TABLE_BY_KEY: dict[str, TableEntry] = {e.key: e for e in TABLE}
MIN_MATCH_SCORE = 2.0

# ----------------------------------------------------------------------------------------------- matching
_SPELLING = {
    "aluminum": "aluminium", "fiberfill": "fibrefill", "fibers": "fibre", "fiber": "fibre",
    "modeling": "modelling", "colored": "coloured", "color": "colour", "polyurethan": "polyurethane",
}


def _norm_token(tok: str) -> str:
    tok = _SPELLING.get(tok, tok)
    if len(tok) > 4 and tok.endswith("oes"):
        tok = tok[:-2]  # tomatoes -> tomato
    elif len(tok) > 4 and tok.endswith("ies"):
        tok = tok[:-3] + "y"  # berries -> berry
    elif len(tok) > 3 and tok.endswith("s") and not tok.endswith(("ss", "us", "is")):
        tok = tok[:-1]  # segments -> segment, balls -> ball
    return _SPELLING.get(tok, tok)


def tokenize(text: str) -> list[str]:
    """Lower-case word tokens with British spelling and simple plurals folded (deterministic)."""
    return [_norm_token(t) for t in re.findall(r"[a-z0-9]+", text.lower())]


def _has_phrase(tokens: list[str], phrase: str) -> bool:
    words = tokenize(phrase)
    n = len(words)
    return any(tokens[i:i + n] == words for i in range(len(tokens) - n + 1))


def score_entries(description: str, name: str = "") -> list[tuple[float, str]]:
    """Keyword score of every table entry for ``description`` + ``name``, best first (ties by table order)."""
    tokens = tokenize(f"{description} {name.replace('_', ' ')}")
    scored = []
    for idx, entry in enumerate(TABLE):
        score = sum(w for phrase, w in entry.keywords if _has_phrase(tokens, phrase))
        scored.append((score, idx, entry.key))
    scored.sort(key=lambda t: (-t[0], t[1]))
    return [(s, k) for s, _, k in scored]


def _known_materials() -> str:
    return ", ".join(f"{e.key} ({e.title})" for e in TABLE)


def match_entry(description: str, name: str = "") -> TableEntry:
    """The table entry that best matches the description; a clear error when none or several tie."""
    scores = score_entries(description, name)
    best_score, best_key = scores[0]
    if best_score < MIN_MATCH_SCORE:
        raise MaterialOracleError(
            f"no material table entry matches object {name!r} (description {description!r}): known materials "
            f"are {_known_materials()}; add a distinguishing word to the description, give explicit values "
            "under the object's material: (model, youngs_modulus, poisson_ratio, density, yield_stress for "
            "plastic models, squeeze_threshold), or use oracle.backend=llm")
    tied = [k for s, k in scores if s == best_score]
    if len(tied) > 1:
        raise MaterialOracleError(
            f"object {name!r}: description {description!r} matches {', '.join(tied)} equally (score "
            f"{best_score:g}): add a distinguishing word (e.g. "
            f"{', '.join(repr(TABLE_BY_KEY[k].keywords[0][0]) for k in tied)}) or give explicit material values")
    return TABLE_BY_KEY[best_key]


def resolve_interior(interior: Optional[str], entry: Optional[TableEntry], name: str = "") -> Optional[str]:
    """The INTERIORS key for the object's ``interior`` string (None -> None).

    The entry's own default interior wins when the string names any of its keywords (``juice`` in a tomato
    is tomato juice); otherwise the best keyword match over all interiors; ties and misses are errors.
    """
    if interior is None:
        return None
    tokens = tokenize(interior)
    if entry is not None and entry.interior is not None:
        default = INTERIORS[entry.interior]
        if "_".join(tokens) == entry.interior or any(_has_phrase(tokens, k) for k in default.keywords):
            return entry.interior
    scores = []
    for idx, item in enumerate(INTERIORS.values()):
        s = sum(1.0 for k in item.keywords if _has_phrase(tokens, k)) + (5.0 if "_".join(tokens) == item.key
                                                                          else 0.0)
        scores.append((s, idx, item.key))
    scores.sort(key=lambda t: (-t[0], t[1]))
    best = scores[0][0]
    tied = [k for s, _, k in scores if s == best]
    if best <= 0:
        raise MaterialOracleError(
            f"object {name!r}: interior {interior!r} matches no known interior material ({', '.join(INTERIORS)})"
            ": name one of them, or set interior: null for a hollow or solid object")
    if len(tied) > 1:
        raise MaterialOracleError(
            f"object {name!r}: interior {interior!r} matches {', '.join(tied)} equally: name one of them "
            f"(e.g. interior: {tied[0]})")
    return tied[0]


# ----------------------------------------------------------------------------------------------- config access
def _get(obj: Any, key: str, default: Any = None) -> Any:
    if obj is None:
        return default
    if isinstance(obj, Mapping):
        return obj.get(key, default)
    return getattr(obj, key, default)


def _read_overrides(overrides: Any, name: str) -> dict[str, Any]:
    """The non-None override values (dataclass, DictConfig, dict or None), type-checked."""
    if overrides is None:
        return {}
    if isinstance(overrides, Mapping):
        unknown = sorted(str(k) for k in overrides.keys() if k not in OVERRIDE_KEYS)
        if unknown:
            raise MaterialOracleError(
                f"object {name!r}: unknown material override(s) {', '.join(unknown)}: allowed keys are "
                f"{', '.join(OVERRIDE_KEYS)}")
    out: dict[str, Any] = {}
    for key in OVERRIDE_KEYS:
        value = _get(overrides, key)
        if value is None:
            continue
        if key == "model":
            out[key] = str(value)
            continue
        if isinstance(value, bool) or not isinstance(value, (int, float, str)):
            raise MaterialOracleError(f"object {name!r}: material.{key} {value!r} is not a number: give it in SI "
                                      "units (e.g. 1.0e6)")
        try:
            out[key] = float(value)
        except ValueError:
            raise MaterialOracleError(f"object {name!r}: material.{key} {value!r} is not a number: give it in SI "
                                      "units (e.g. 1.0e6)") from None
    return out


@dataclass(frozen=True)
class _Cfg:
    backend: str
    llm_url: Optional[str]
    llm_model: str
    api_key_env: str
    timeout_s: float
    cache_dir: Optional[str]


def _read_cfg(cfg: Any) -> _Cfg:
    backend = str(_get(cfg, "backend", "table"))
    if backend not in ("table", "llm"):
        raise MaterialOracleError(f"oracle.backend {backend!r} must be 'table' or 'llm'")
    timeout_s = _get(cfg, "timeout_s", 20.0)
    try:
        timeout_s = float(timeout_s)
    except (TypeError, ValueError):
        raise MaterialOracleError(f"oracle.timeout_s {timeout_s!r} is not a number of seconds") from None
    if not (math.isfinite(timeout_s) and timeout_s > 0):
        raise MaterialOracleError(f"oracle.timeout_s {timeout_s:g} must be > 0 s")
    url = _get(cfg, "llm_url")
    cache_dir = _get(cfg, "cache_dir")
    return _Cfg(backend=backend, llm_url=None if url is None else str(url),
                llm_model=str(_get(cfg, "llm_model", "gpt-5")),
                api_key_env=str(_get(cfg, "api_key_env", "VIRSQUEEZER_LLM_API_KEY")),
                timeout_s=timeout_s, cache_dir=None if cache_dir is None else str(cache_dir))


# ----------------------------------------------------------------------------------------------- oracle
def material_oracle(description: str, name: str = "", overrides: Any = None, interior: Optional[str] = None,
                    cfg: Any = None) -> ObjectMaterials:
    """Physical properties of one object from its text description.

    Args:
        description: free text (``ObjectConfig.description``).
        name: the object's config name (``ObjectConfig.name``); it also counts for table matching.
        overrides: ``MaterialOverrides``-like (dataclass, DictConfig, dict, None); every non-None value wins
            over the backend's (shell model/E/nu/density/yield_stress, squeeze_threshold).
        interior: ``ObjectConfig.interior``; ``None`` means no interior material is returned at all.
        cfg: ``OracleConfig``-like; ``None`` = offline table.

    Returns the validated :class:`ObjectMaterials`.  Raises :class:`MaterialOracleError` (one line) when the
    description matches nothing, a value is invalid, or the LLM endpoint fails.
    """
    if not isinstance(description, str) or not description.strip():
        raise MaterialOracleError(f"object {name!r}: description is empty: describe what the object is made of")
    if interior is not None and not isinstance(interior, str):
        raise MaterialOracleError(f"object {name!r}: interior {interior!r} must be a string or null")
    conf = _read_cfg(cfg)
    values = _read_overrides(overrides, name)
    pre_notes = []
    if interior is not None and interior.strip().lower() in NO_INTERIOR:
        pre_notes.append(f"interior {interior!r} is not simulated: treated as interior: null")
        interior = None

    if conf.backend == "llm":
        answer = _llm_answer(description, name, interior, conf)
        base = dict(shell=answer.shell, interior=answer.interior, squeeze_threshold=answer.squeeze_threshold,
                    threshold_source=answer.threshold_source, effect=answer.effect,
                    matched_entry=f"llm:{conf.llm_model}", backend="llm", notes=[])
        if interior is None and answer.interior is not None:
            base["notes"].append(f"interior {(answer.interior.name or answer.interior.model)!r} from the LLM "
                                 "dropped: the object config has interior: null")
            base["interior"] = None
        elif interior is not None and answer.interior is None:
            base["notes"].append(f"the LLM gave no interior material for interior {interior!r}")
    else:
        base = _table_answer(description, name, interior, values)

    base["notes"] = pre_notes + base["notes"]
    return _apply_overrides(base, values, name)


def _table_answer(description: str, name: str, interior: Optional[str], values: dict[str, Any]) -> dict:
    try:
        entry = match_entry(description, name)
    except MaterialOracleError:
        explicit = _explicit_shell(values)
        if explicit is None:
            raise
        ikey = resolve_interior(interior, None, name)
        return dict(shell=explicit, interior=_interior_material(ikey), core=_core_material(ikey),
                    squeeze_threshold=None, threshold_source="", effect="none", matched_entry="explicit",
                    backend="explicit",
                    notes=["no table entry matched: the shell comes from the object's explicit material values"])
    notes = []
    key = resolve_interior(interior, entry, name)
    if interior is None and entry.interior is not None:
        notes.append(f"interior {entry.interior!r} of table entry {entry.key!r} dropped: the object config has "
                     "interior: null")
    elif key is not None:
        notes.append(f"interior {interior!r} -> table interior {key!r}")
    return dict(shell=entry.shell, interior=_interior_material(key), core=_core_material(key),
                squeeze_threshold=entry.squeeze_threshold,
                threshold_source=entry.threshold_source, effect=entry.effect, matched_entry=entry.key,
                backend="table", notes=notes)


def _interior_material(key: Optional[str]) -> Optional[MaterialProperties]:
    return None if key is None else INTERIORS[key].material


def _core_material(key: Optional[str]) -> Optional[MaterialProperties]:
    return None if key is None else INTERIORS[key].core


def _explicit_shell(values: dict[str, Any]) -> Optional[MaterialProperties]:
    """A shell built only from override values, when they are complete enough (else None)."""
    needed = ["model", "youngs_modulus", "poisson_ratio", "density"]
    if values.get("model") in PLASTIC_MODELS:
        needed.append("yield_stress")
    if any(k not in values for k in needed) or values.get("model") == "fluid":
        return None
    data = {k: values[k] for k in SHELL_OVERRIDE_KEYS if k in values}
    try:
        return MaterialProperties(name="explicit", source="explicit values in the object config", **data)
    except ValidationError as exc:
        raise MaterialOracleError(f"explicit material values: {one_line(exc)}") from None


def _apply_overrides(base: dict, values: dict[str, Any], name: str) -> ObjectMaterials:
    shell: MaterialProperties = base["shell"]
    shell_over = {k: values[k] for k in SHELL_OVERRIDE_KEYS if k in values}
    notes = list(base["notes"])
    if shell_over and base["backend"] != "explicit":
        data = shell.model_dump()
        changed = ", ".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in shell_over.items())
        data.update(shell_over)
        data["source"] = f"{shell.source}; overridden by the object config: {changed}"
        try:
            shell = MaterialProperties.model_validate(data)
        except ValidationError as exc:
            raise MaterialOracleError(
                f"object {name!r}: material override ({changed}) gives an invalid shell: {one_line(exc)}") from None
        notes.append(f"shell overridden by the object config: {changed}")
    threshold, threshold_source = base["squeeze_threshold"], base["threshold_source"]
    if "squeeze_threshold" in values:
        threshold = values["squeeze_threshold"]
        threshold_source = "explicit material.squeeze_threshold in the object config"
        notes.append(f"squeeze_threshold overridden by the object config: {threshold:g}")
    try:
        return ObjectMaterials(shell=shell, interior=base["interior"], core=base.get("core"),
                               squeeze_threshold=threshold,
                               threshold_source=threshold_source, effect=base["effect"],
                               matched_entry=base["matched_entry"], backend=base["backend"], notes=notes)
    except ValidationError as exc:
        raise MaterialOracleError(f"object {name!r}: {one_line(exc)}") from None


def oracle_for_object(obj: Any, cfg: Any = None) -> ObjectMaterials:
    """:func:`material_oracle` for an ``ObjectConfig``-like object (dataclass or DictConfig)."""
    return material_oracle(str(_get(obj, "description", "")), str(_get(obj, "name", "")),
                           _get(obj, "material"), _get(obj, "interior"), cfg)


def materials_to_dict(materials: ObjectMaterials) -> dict[str, Any]:
    """JSON-able dict for artifact attributes: every field plus derived moduli and wave speeds (SI).

    ``materials_from_dict`` reverses it (the ``derived`` block is recomputed, not read).
    """
    out = materials.model_dump(mode="json")
    derived: dict[str, Any] = {}
    for part in ("shell", "interior", "core"):
        m = getattr(materials, part)
        if m is not None:
            derived[part] = {"shear_modulus": m.shear_modulus, "lame_lambda": m.lame_lambda,
                             "bulk_modulus": m.bulk_modulus, "wave_speed": m.wave_speed,
                             "units": {"shear_modulus": "Pa", "lame_lambda": "Pa", "bulk_modulus": "Pa",
                                       "wave_speed": "m/s"}}
    out["derived"] = derived
    out["units"] = {"youngs_modulus": "Pa", "poisson_ratio": "1", "density": "kg/m^3", "yield_stress": "Pa",
                    "viscosity": "Pa s", "hardening": "Pa", "squeeze_threshold": "1"}
    return json.loads(json.dumps(out, allow_nan=False))


def mpm_material_kwargs(material: MaterialProperties, name: str = "") -> dict[str, Any]:
    """Keyword arguments for the MPM solver's ``tasks.physics.mpm.materials.Material`` (``material_from_dict``).

    ``None`` becomes 0 (no yield / hardening / viscosity); a fluid passes its bulk modulus explicitly.
    """
    out: dict[str, Any] = {
        "name": name or material.name or material.model, "model": material.model,
        "youngs_modulus": material.youngs_modulus, "poisson_ratio": material.poisson_ratio,
        "density": material.density, "yield_stress": material.yield_stress or 0.0,
        "hardening": material.hardening or 0.0, "viscosity": material.viscosity or 0.0}
    if material.model == "fluid":
        out["bulk_modulus"] = material.bulk_modulus
    return out


def materials_from_dict(data: Mapping[str, Any]) -> ObjectMaterials:
    """Inverse of :func:`materials_to_dict`."""
    clean = {k: v for k, v in data.items() if k not in ("derived", "units")}
    return ObjectMaterials.model_validate(clean)


# ----------------------------------------------------------------------------------------------- LLM backend
_SYSTEM_PROMPT = """You are a materials engineer preparing inputs for a Material Point Method (MPM) simulation \
of an object squeezed by a human hand. From the object's name, description and interior, infer real physical \
properties in SI units and answer with ONE JSON object, no prose, that validates against this JSON schema:
{schema}
Rules:
- Units: Pa, kg/m^3, Pa s. Poisson's ratio 0 <= nu <= 0.49 (never 0.5). Give real measured values where \
they exist and name the handbook or paper in "source"; say "engineering choice" where you chose a value.
- "shell" is the visible body or wall; "interior" is what fills it (null when the object is hollow or solid).
- Models: fixed_corotated / neo_hookean (elastic), stvk_hencky_von_mises (elastoplastic, needs yield_stress), \
foam (viscoplastic, needs yield_stress), fluid (needs viscosity; give youngs_modulus = 3 K (1 - 2 nu) with \
nu = 0.49 so that K is the liquid's bulk modulus).
- "squeeze_threshold" is the compressive engineering strain (0..1) at the finger contact where rupture or \
overflow starts; null if the object never ruptures when squeezed by hand. Effects juice, cola_spray and \
stuffing_spill need a threshold; rebound, dent, buckle and none usually have null.
"""


def _prompt_messages(description: str, name: str, interior: Optional[str]) -> list[dict[str, str]]:
    schema = json.dumps(LLMAnswer.model_json_schema(), sort_keys=True)
    user = json.dumps({"name": name, "description": description, "interior": interior}, sort_keys=True)
    return [{"role": "system", "content": _SYSTEM_PROMPT.format(schema=schema)},
            {"role": "user", "content": f"Object (JSON): {user}"}]


def _display_url(url: str) -> str:
    """The URL without user info and query string (they may hold credentials)."""
    try:
        u = httpx.URL(url)
        return str(u.copy_with(username=None, password=None, query=None, fragment=None))
    except Exception:  # noqa: BLE001 - a malformed URL is reported as given, minus anything after '?'
        return url.split("?", 1)[0]


class _Redactor:
    def __init__(self, secret: Optional[str]) -> None:
        self.secret = secret

    def __call__(self, text: str) -> str:
        if self.secret:
            text = text.replace(self.secret, "***")
        return text


def _cache_key(conf: _Cfg, description: str, name: str, interior: Optional[str]) -> tuple[str, dict[str, Any]]:
    key = {"url": conf.llm_url, "model": conf.llm_model, "description": description, "name": name,
           "interior": interior, "prompt_version": PROMPT_VERSION}
    digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()
    return digest, key


def _cache_read(path: Path, key_display: dict[str, Any]) -> Optional[LLMAnswer]:
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
        if record.get("key") != key_display:
            log.warning("material cache %s belongs to another request: ignored", path)
            return None
        return LLMAnswer.model_validate(record["answer"])
    except FileNotFoundError:
        return None
    except (OSError, ValueError, KeyError, TypeError, ValidationError) as exc:
        log.warning("material cache %s is unreadable (%s): asking the endpoint again", path, type(exc).__name__)
        return None


def _cache_write(path: Path, key_display: dict[str, Any], answer: LLMAnswer) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    record = {"key": key_display, "answer": answer.model_dump(mode="json"),
              "created_unix": time.time(), "format": "virsqueezer-material-cache-v1"}
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    tmp.write_text(json.dumps(record, indent=1, sort_keys=True), encoding="utf-8")
    os.replace(tmp, path)


def _llm_answer(description: str, name: str, interior: Optional[str], conf: _Cfg) -> LLMAnswer:
    if not conf.llm_url:
        raise MaterialOracleError("oracle.llm_url is not set: give the base URL of an OpenAI-compatible "
                                  "API (e.g. http://127.0.0.1:8000/v1) or use backend=table")
    if not conf.llm_url.startswith(("http://", "https://")):
        raise MaterialOracleError(f"oracle.llm_url {_display_url(conf.llm_url)!r} must start with "
                                  "http:// or https://")
    digest, key = _cache_key(conf, description, name, interior)
    key_display = dict(key, url=_display_url(conf.llm_url), url_sha256=hashlib.sha256(
        conf.llm_url.encode()).hexdigest())
    cache_path = Path(conf.cache_dir) / f"{digest}.json" if conf.cache_dir else None
    if cache_path is not None:
        cached = _cache_read(cache_path, key_display)
        if cached is not None:
            log.info("material oracle: cached LLM answer for %r (%s)", name, cache_path.name)
            return cached
    answer = _ask_llm(description, name, interior, conf)
    if cache_path is not None:
        _cache_write(cache_path, key_display, answer)
    return answer


def _ask_llm(description: str, name: str, interior: Optional[str], conf: _Cfg) -> LLMAnswer:
    assert conf.llm_url is not None
    endpoint = conf.llm_url.rstrip("/") + "/chat/completions"
    shown = _display_url(endpoint)
    secret = os.environ.get(conf.api_key_env) or None
    redact = _Redactor(secret)
    headers = {"Content-Type": "application/json", "Accept": "application/json"}
    if secret:
        headers["Authorization"] = f"Bearer {secret}"
    payload = {"model": conf.llm_model, "messages": _prompt_messages(description, name, interior),
               "response_format": {"type": "json_object"}, "temperature": 0}

    def fail(msg: str) -> MaterialOracleError:
        return MaterialOracleError(redact(msg))

    timeout_msg = (f"LLM endpoint {shown} timed out after {conf.timeout_s:g} s: raise oracle.timeout_s "
                   "or use backend=table")
    log.info("material oracle: asking %s (model %s) about %r", shown, conf.llm_model, name)
    deadline = time.monotonic() + conf.timeout_s
    try:
        # trust_env=False: no proxy or netrc from the environment - only llm_url is ever contacted
        with httpx.Client(timeout=httpx.Timeout(conf.timeout_s), trust_env=False, follow_redirects=False) as client:
            with client.stream("POST", endpoint, json=payload, headers=headers) as resp:
                chunks, size = [], 0
                for chunk in resp.iter_bytes():
                    chunks.append(chunk)
                    size += len(chunk)
                    if time.monotonic() > deadline:
                        raise fail(timeout_msg)
                    if size > MAX_RESPONSE_BYTES:
                        raise fail(f"LLM endpoint {shown} answered more than {MAX_RESPONSE_BYTES} bytes: not a "
                                   "material answer")
                body = b"".join(chunks)
                status = resp.status_code
    except httpx.TimeoutException:
        raise fail(timeout_msg) from None
    except httpx.HTTPError as exc:
        raise fail(f"LLM endpoint {shown} is unreachable ({type(exc).__name__}): start the server, fix "
                   "oracle.llm_url or use backend=table") from None
    text = body.decode("utf-8", errors="replace")
    if status != 200:
        hint = f" (check the API key in ${conf.api_key_env})" if status in (401, 403) else ""
        raise fail(f"LLM endpoint {shown} answered HTTP {status}{hint}: {_snippet(text)}")
    try:
        envelope = json.loads(text)
    except ValueError as exc:
        raise fail(f"LLM endpoint {shown} returned a body that is not JSON ({exc.msg} at char {exc.pos}): "
                   f"{_snippet(text)}") from None
    try:
        message = envelope["choices"][0]["message"]
        content = message.get("content")
    except (KeyError, IndexError, TypeError, AttributeError):
        raise fail(f"LLM endpoint {shown} answered without choices[0].message (not an OpenAI-compatible chat "
                   f"completion): {_snippet(text)}") from None
    if content is None and message.get("refusal"):
        raise fail(f"LLM endpoint {shown} refused: {_snippet(str(message['refusal']))}")
    if isinstance(content, str):
        stripped = content.strip()
        fence = re.fullmatch(r"```(?:json)?\s*(.*?)\s*```", stripped, flags=re.S)
        if fence:
            stripped = fence.group(1)
        try:
            data = json.loads(stripped)
        except ValueError as exc:
            raise fail(f"LLM endpoint {shown} answered invalid JSON in choices[0].message.content ({exc.msg} at "
                       f"char {exc.pos}): {_snippet(stripped)}") from None
    elif isinstance(content, dict):
        data = content
    else:
        raise fail(f"LLM endpoint {shown} answered choices[0].message.content of type "
                   f"{type(content).__name__}: expected a JSON string")
    if not isinstance(data, dict):
        raise fail(f"LLM endpoint {shown} answered JSON {type(data).__name__}, expected an object")
    try:
        return LLMAnswer.model_validate(data)
    except ValidationError as exc:
        raise fail(f"LLM endpoint {shown} answered JSON that violates the material schema: {one_line(exc)}") \
            from None


def _snippet(text: str, limit: int = 160) -> str:
    text = " ".join(text.split())
    return repr(text[:limit] + ("..." if len(text) > limit else ""))


# ----------------------------------------------------------------------------------------------- Prefect step


@artifact_step("material_oracle",
               reads=("object.description", "object.name", "object.material", "object.interior", "oracle"))
def material_oracle_step(inputs, params):
    """Physical properties of one object from its description (sec. 3.2); values under ``object.material`` win.
    The result is small: it lives in the artifact's attributes (``materials``), no arrays."""
    mats = material_oracle(params["object.description"], params["object.name"], params["object.material"],
                           params["object.interior"], params["oracle"])
    return {}, {"materials": materials_to_dict(mats)}
