"""The material oracle's offline table (paper sec. 3.2): real material properties per object kind, each with the
source of its values, read from ``materials.yaml`` and validated.

The file's layout is described in its header.  SI units: Pa, kg/m^3, Pa s.  A fluid gives its physical bulk
modulus K; it is stored as the equivalent elastic pair ``youngs_modulus = 3 K (1 - 2 poisson_ratio)`` (see
:mod:`tasks.physics.oracle.schema`).  A bad value raises :class:`MaterialTableError` naming the file, the entry
and the field.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import yaml
from pydantic import BaseModel, ConfigDict, ValidationError

from tasks.physics.oracle.schema import MaterialOracleError, MaterialProperties, ObjectMaterials, one_line

DATA_FILES: tuple[str, ...] = ("materials.yaml",)  # next to this module; its content is the table
TABLE_PATH = Path(__file__).with_name(DATA_FILES[0])


class MaterialTableError(MaterialOracleError):
    """The material table file is unreadable or holds an invalid entry; the message names the entry and field."""


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
    """An interior material; ``core`` is the solid tissue that holds it inside the body (see the schema doc)."""

    key: str
    keywords: tuple[str, ...]
    material: MaterialProperties
    core: Optional[MaterialProperties] = None


class _MaterialRecord(BaseModel):
    """A material as written in the file: a fluid gives ``bulk_modulus`` (Pa) instead of ``youngs_modulus``."""

    model_config = ConfigDict(extra="allow")

    bulk_modulus: Optional[float] = None

    def material(self) -> MaterialProperties:
        data: dict[str, Any] = dict(self.model_extra or {})
        if self.bulk_modulus is not None:
            if data.get("model") != "fluid" or "youngs_modulus" in data:
                raise ValueError("bulk_modulus is only for a fluid, in place of youngs_modulus")
            data["youngs_modulus"] = 3.0 * self.bulk_modulus * (1.0 - 2.0 * data.get("poisson_ratio", 0.0))
        return MaterialProperties.model_validate(data)


class _InteriorRecord(BaseModel):
    model_config = ConfigDict(extra="forbid")

    keywords: tuple[str, ...]
    material: _MaterialRecord
    core: Optional[_MaterialRecord] = None


class _EntryRecord(BaseModel):
    model_config = ConfigDict(extra="forbid")

    title: str
    keywords: dict[str, float]
    shell: _MaterialRecord
    interior: Optional[str]
    squeeze_threshold: Optional[float]
    threshold_source: str
    effect: str


class _TableFile(BaseModel):
    model_config = ConfigDict(extra="forbid")

    interiors: dict[str, _InteriorRecord]
    entries: dict[str, _EntryRecord]


def _material(record: _MaterialRecord, where: str, path: Path) -> MaterialProperties:
    try:
        return record.material()
    except ValidationError as exc:
        raise MaterialTableError(f"{path}: {one_line(exc, tuple(where.split('.')))}: fix the file") from None
    except ValueError as exc:
        raise MaterialTableError(f"{path}: {where}: {exc}: fix the file") from None


def load_table(path: Path = TABLE_PATH) -> tuple[tuple[TableEntry, ...], dict[str, InteriorEntry]]:
    """The table entries (in matching order) and the interiors by key, read from ``path`` and validated.

    Every material is a :class:`MaterialProperties`; every entry's interior, threshold and effect are checked
    as in an :class:`ObjectMaterials`.  Raises :class:`MaterialTableError` with one line naming the entry and
    field (e.g. ``entries.tomato.shell.density``)."""
    try:
        raw = yaml.safe_load(path.read_text(encoding="utf-8"))
        data = _TableFile.model_validate(raw)
    except (OSError, yaml.YAMLError) as exc:
        raise MaterialTableError(f"{path}: unreadable material table ({type(exc).__name__}): restore the file") \
            from None
    except ValidationError as exc:
        raise MaterialTableError(f"{path}: {one_line(exc)}: fix the file") from None
    interiors = {key: InteriorEntry(key, rec.keywords, _material(rec.material, f"interiors.{key}.material", path),
                                    None if rec.core is None else _material(rec.core, f"interiors.{key}.core", path))
                 for key, rec in data.interiors.items()}
    entries = []
    for key, rec in data.entries.items():
        entry = TableEntry(key=key, title=rec.title, keywords=tuple(rec.keywords.items()),
                           shell=_material(rec.shell, f"entries.{key}.shell", path), interior=rec.interior,
                           squeeze_threshold=rec.squeeze_threshold, threshold_source=rec.threshold_source,
                           effect=rec.effect)
        if entry.interior is not None and entry.interior not in interiors:
            raise MaterialTableError(f"{path}: entries.{key}.interior {entry.interior!r} is not one of the interiors "
                                     f"({', '.join(interiors)}): fix the file")
        inside = None if entry.interior is None else interiors[entry.interior]
        try:
            ObjectMaterials(shell=entry.shell, interior=inside and inside.material, core=inside and inside.core,
                            squeeze_threshold=entry.squeeze_threshold, threshold_source=entry.threshold_source,
                            effect=entry.effect, matched_entry=key)
        except ValidationError as exc:
            raise MaterialTableError(f"{path}: {one_line(exc, ('entries', key))}: fix the file") from None
        entries.append(entry)
    return tuple(entries), interiors


TABLE, INTERIORS = load_table()
TABLE_BY_KEY: dict[str, TableEntry] = {e.key: e for e in TABLE}
