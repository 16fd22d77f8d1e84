"""What a weights folder holds, what is missing, and the exact commands that fetch it (nothing is downloaded).

    python -m flows.weights check /path/to/models

The folder layout the runs read (each part optional):

    /path/to/models/stable-diffusion/          generation.weights=/path/to/models (diffusers format, three folders)
    /path/to/models/motion-adapter/
    /path/to/models/controlnet-depth/
    /path/to/models/musiq_spaq_ckpt-358bb6af.pth   paper_metrics.musiq_weights=...
    /path/to/models/amt-s.pth                      paper_metrics.amt_weights=...
    /path/to/models/videophy_2_auto/               paper_metrics.videophy_weights=...

Each model is checked by its files only (configs and weight files, nothing loaded), as the pre-flight check does.
Prints one line per model (present with its size, or missing with why and the ``hf download`` command that fetches
it), the other entries of the folder, and the overrides that use what is present.  Exit status 0 when everything is
present, 1 otherwise.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from tasks.evaluation.paper_weights import PAPER_WEIGHTS
from tasks.generation.components import _MODEL_SPECS, DiffusionWeights, check_weights


def _size_gb(path: Path) -> float:
    files = [path] if path.is_file() else [p for p in path.rglob("*") if p.is_file() and ".cache" not in p.parts]
    return sum(p.stat().st_size for p in files) / 1e9


def inventory(folder: Path) -> tuple[list[str], bool]:
    """The report lines for ``folder`` and whether every model is present."""
    lines, commands, overrides, known = [], [], [], set()
    weights = DiffusionWeights(folder=str(folder))
    missing = {m.model: m for m in check_weights(weights)}
    lines.append(f"weights folder {folder}")
    for spec in _MODEL_SPECS:
        sub = getattr(weights, spec.key).subfolder
        known.add(sub)
        if spec.name in missing:
            m = missing[spec.name]
            lines.append(f"  missing  {spec.name:52s} {sub}/ ({m.problem})")
            commands.append(m.command)
        else:
            lines.append(f"  present  {spec.name:52s} {sub}/ ({_size_gb(folder / sub):.2f} GB)")
    if not missing:
        overrides.append(f"generation.weights={folder}")
    for spec in PAPER_WEIGHTS:
        path = folder / spec.file
        known.add(spec.file)
        reason = spec.reason(str(path))
        if reason is None:
            lines.append(f"  present  {spec.heading:52s} {spec.file} ({_size_gb(path):.2f} GB)")
            overrides.append(f"{spec.key}={path}")
        else:
            lines.append(f"  missing  {spec.heading:52s} {spec.file}")
            commands.append(spec.command(path))
    others = sorted(p.name for p in folder.iterdir() if p.name not in known and not p.name.startswith(".")) \
        if folder.is_dir() else []
    if others:
        lines.append("  other entries (not read by the runs): " + ", ".join(others))
    if commands:
        lines.append("fetch what is missing (on a machine with internet; then copy the folder here):")
        lines += [f"  {command}" for command in commands]
    if overrides:
        lines.append("use what is present:")
        lines.append("  python -m flows.evaluate " + " ".join(overrides))
    return lines, not commands


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m flows.weights", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    check = sub.add_parser("check", help="list what a weights folder holds, what is missing and how to fetch it")
    check.add_argument("folder", type=Path)
    args = parser.parse_args(argv)
    folder = args.folder.expanduser().resolve()
    if folder.exists() and not folder.is_dir():
        print(f"{folder} is a file, not a folder: pass the folder that holds (or will hold) the models",
              file=sys.stderr)
        return 2
    lines, complete = inventory(folder)
    print("\n".join(lines))
    return 0 if complete else 1


if __name__ == "__main__":
    sys.exit(main())
