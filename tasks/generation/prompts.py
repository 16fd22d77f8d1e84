"""Text prompts for the secondary-effect generation (paper sec. 3.3: the textual prompt joins the G-buffer conditions).

The prompt names the squeezed object and its effect (liquid spraying from a can or fruit, stuffing spilling from a
plush toy); the negative prompt lists the usual Stable Diffusion failure modes. Both are overridable from config.
"""

import re
from dataclasses import dataclass

EFFECT_PHRASES = {
    "liquid": "{material} bursting and spraying out of the {name}, splashing droplets",
    "stuffing": "fluffy {material} spilling out of the torn {name}, loose fibres",
}
STYLE = "photorealistic, high detail"
NEGATIVE_PROMPT = "blurry, low quality, distorted, deformed hand, extra fingers, cartoon, watermark, text"
_SUBJECT_END = re.compile(r";|,| with | made of | filled ")


@dataclass(frozen=True)
class EffectPrompt:
    """Positive and negative prompt of one object's effect generation."""

    prompt: str
    negative_prompt: str


def _subject(display_name: str, description: str) -> str:
    """The object as a short noun phrase: the description's first clause ("A ripe red tomato"), else its name."""
    clause = _SUBJECT_END.split(description.strip(), maxsplit=1)[0].strip()
    if not clause:
        return f"a {display_name.strip().lower()}"
    return clause[0].lower() + clause[1:]


def effect_prompt(
    display_name: str,
    description: str,
    interior_material: str,
    effect: str,
    prompt_override: str | None = None,
    negative_override: str | None = None,
) -> EffectPrompt:
    """The prompt for squeezing this object past its threshold (paper sec. 3.3), e.g. for the tomato
    "a hand squeezing a ripe red tomato, pulp bursting and spraying out of the tomato, splashing droplets,
    photorealistic, high detail". `effect` is "liquid" or "stuffing"; an override replaces the built text verbatim.
    """
    if effect not in EFFECT_PHRASES:
        raise ValueError(f"effect must be one of {sorted(EFFECT_PHRASES)}, got {effect!r}; set the effect kind")
    if not display_name.strip() or not interior_material.strip():
        raise ValueError("display_name and interior_material must be non-empty; set them in the object config")
    phrase = EFFECT_PHRASES[effect].format(material=interior_material.strip(), name=display_name.strip().lower())
    built = f"a hand squeezing {_subject(display_name, description)}, {phrase}, {STYLE}"
    return EffectPrompt(
        prompt=built if prompt_override is None else prompt_override,
        negative_prompt=NEGATIVE_PROMPT if negative_override is None else negative_override,
    )
