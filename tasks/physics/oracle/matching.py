"""Matching an object's description to the material table (paper sec. 3.2, offline backend of the oracle):
deterministic keyword scores over word tokens with British spelling and simple plurals folded."""
from __future__ import annotations

import re
from typing import Optional

from tasks.physics.oracle.schema import MaterialOracleError
from tasks.physics.oracle.table import INTERIORS, TABLE, TABLE_BY_KEY, TableEntry

# ``interior`` strings that mean "nothing simulated inside" (a hollow object's air is not an MPM material)
NO_INTERIOR: tuple[str, ...] = ("air", "none", "null", "empty", "hollow", "nothing", "gas")

MIN_MATCH_SCORE = 2.0  # 1, the smallest keyword score that counts as a match

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
