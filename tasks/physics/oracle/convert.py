"""The oracle's materials as plain data: artifact attributes (JSON) and keyword arguments of the MPM solver's
materials (paper sec. 3.2).  SI units: Pa, kg/m^3, Pa s, m/s."""
from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

from tasks.physics.oracle.schema import MaterialProperties, ObjectMaterials


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
