"""Material oracle: an object's text description -> physical properties for the MPM simulation.

Paper, sec. 3.2 ("Squeezing-Driven Deformation"): before the MPM simulation an LLM (GPT-5) infers the object's
material type, Young's modulus, Poisson's ratio and yield strength, and a *squeezing threshold*: when the
deformation exceeds it, objects with suitable materials show secondary effects (rupture, overflow); below it
they only deform and e.g. rebound on release.  Interior particles (juice, cola, stuffing) get their own
material on the same MPM grid.

This module gives that step two backends behind one pure function, :func:`material_oracle`:

* ``table`` (default, offline, deterministic): the curated table of real material properties in
  ``tasks/physics/oracle/materials.yaml``, each with a ``source`` saying where the numbers come from and how
  sure they are.  A description (+ the object's name) is matched to an entry by keyword scores
  (:mod:`tasks.physics.oracle.matching`).
* ``llm``: any OpenAI-compatible chat-completions endpoint (:mod:`tasks.physics.oracle.llm`).

Explicit values in the object's ``material`` overrides always win and the merged result is validated again.
The schema, its units and the conventions the simulator relies on are in :mod:`tasks.physics.oracle.schema`.
"""
from __future__ import annotations

from typing import Any, Optional

from pydantic import ValidationError

from tasks.core.step import artifact_step
from tasks.physics.oracle.config import SHELL_OVERRIDE_KEYS, config_field, read_overrides, read_settings
from tasks.physics.oracle.convert import materials_from_dict, materials_to_dict, mpm_material_kwargs
from tasks.physics.oracle.llm import llm_answer
from tasks.physics.oracle.matching import NO_INTERIOR, match_entry, resolve_interior
from tasks.physics.oracle.schema import (
    PLASTIC_MODELS,
    LLMAnswer,
    MaterialOracleError,
    MaterialProperties,
    ObjectMaterials,
    one_line,
    validate_material,
)
from tasks.physics.oracle.table import INTERIORS, TABLE

# what other modules import from here (the step's library lives in tasks.physics.oracle)
__all__ = ["INTERIORS", "TABLE", "LLMAnswer", "MaterialOracleError", "MaterialProperties", "ObjectMaterials",
           "match_entry", "material_oracle", "material_oracle_step", "materials_from_dict", "materials_to_dict",
           "mpm_material_kwargs", "oracle_for_object", "validate_material"]


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
    conf = read_settings(cfg)
    values = read_overrides(overrides, name)
    pre_notes = []
    if interior is not None and interior.strip().lower() in NO_INTERIOR:
        pre_notes.append(f"interior {interior!r} is not simulated: treated as interior: null")
        interior = None

    if conf.backend == "llm":
        answer = llm_answer(description, name, interior, conf)
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
    return material_oracle(str(config_field(obj, "description", "")), str(config_field(obj, "name", "")),
                           config_field(obj, "material"), config_field(obj, "interior"), cfg)


@artifact_step("material_oracle",
               reads=("object.description", "object.name", "object.material", "object.interior", "oracle"))
def material_oracle_step(inputs, params):
    """Physical properties of one object from its description (sec. 3.2); values under ``object.material`` win.
    The result is small: it lives in the artifact's attributes (``materials``), no arrays."""
    mats = material_oracle(params["object.description"], params["object.name"], params["object.material"],
                           params["object.interior"], params["oracle"])
    return {}, {"materials": materials_to_dict(mats)}
