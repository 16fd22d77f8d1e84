"""The home page's picture: the eight objects at rest, at the peak squeeze and after the release (view 0 of each
object's contact sheet in a main-job report), as one small PNG.

    python docs/_tools/contact_sheet.py reports/evaluate-<time> docs/images/contact-sheet.png

Each report holds ``<object>_contact_sheet.png`` (:func:`tasks.reporting.watch.object_media`): rows the views,
columns rest / peak squeeze / after release, with a label band of ``label_px`` on top and a label column of
``row_label_px`` on the left (:func:`tasks.reporting.video.contact_sheet`). This script cuts out each sheet's view-0
row, scales its three frames to ``--tile`` pixels and tiles them as rows = moments, columns = objects, labelled by the
same function.
"""
from __future__ import annotations

import argparse
import inspect
import sys
from pathlib import Path

import numpy as np
from PIL import Image

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from tasks.reporting.video import contact_sheet  # noqa: E402

OBJECTS = ("can", "plush_toy", "rubber_duck", "clay", "tomato", "orange", "rubber_ball", "paper_cup")
MOMENTS = ("rest", "peak squeeze", "after release")
_DEFAULTS = inspect.signature(contact_sheet).parameters
LABEL_PX, ROW_LABEL_PX = _DEFAULTS["label_px"].default, _DEFAULTS["row_label_px"].default


def view0_frames(sheet_path: Path) -> np.ndarray:
    """(moment, y, x, 3) uint8: the view-0 row of one object's contact sheet, without its labels."""
    sheet = np.asarray(Image.open(sheet_path).convert("RGB"))
    width = (sheet.shape[1] - ROW_LABEL_PX) // len(MOMENTS)
    views = (sheet.shape[0] - LABEL_PX) / width
    if width <= 0 or views != int(views):
        raise SystemExit(f"{sheet_path}: {sheet.shape[1]} x {sheet.shape[0]} px is not a sheet of square frames, "
                         f"{len(MOMENTS)} columns, {LABEL_PX} px labels on top and {ROW_LABEL_PX} px on the left")
    row = sheet[LABEL_PX:LABEL_PX + width, ROW_LABEL_PX:ROW_LABEL_PX + len(MOMENTS) * width]
    return np.stack([row[:, k * width:(k + 1) * width] for k in range(len(MOMENTS))])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("report", type=Path, help="a main-job report folder, reports/evaluate-<time>")
    parser.add_argument("out", type=Path, help="the PNG to write, e.g. docs/images/contact-sheet.png")
    parser.add_argument("--tile", type=int, default=128, help="pixels per frame in the picture (default 128)")
    args = parser.parse_args(argv)
    missing = [o for o in OBJECTS if not (args.report / f"{o}_contact_sheet.png").is_file()]
    if missing:
        raise SystemExit(f"{args.report} has no contact sheet of {', '.join(missing)}: give a finished main-job report")
    tiles = np.empty((len(MOMENTS), len(OBJECTS), args.tile, args.tile, 3), np.uint8)
    for j, obj in enumerate(OBJECTS):
        for i, frame in enumerate(view0_frames(args.report / f"{obj}_contact_sheet.png")):
            tiles[i, j] = np.asarray(Image.fromarray(frame).resize((args.tile, args.tile), Image.LANCZOS))
    picture = contact_sheet(tiles, list(MOMENTS), [o.replace("_", " ") for o in OBJECTS])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(picture).save(args.out, optimize=True)
    print(f"{args.out}: {picture.shape[1]} x {picture.shape[0]} px, {args.out.stat().st_size / 1e3:.0f} kB")


if __name__ == "__main__":
    main()
