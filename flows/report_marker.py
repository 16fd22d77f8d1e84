"""A report folder being written carries ``REPORT_INCOMPLETE.txt`` until its last file is written (issue 49): a run
stopped (SIGTERM, Ctrl-C) or failing while it writes its report leaves the marker, its stop line says "report
incomplete" (:func:`flows.lifecycle.stop_line`), and the next run of the same config writes its report into that
same folder again (:func:`incomplete_report`) instead of leaving the cut one beside a new one."""
from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Iterator

INCOMPLETE = "REPORT_INCOMPLETE.txt"


def incomplete_report(reports: Path, flow_label: str, digest: str) -> Path | None:
    """The newest report folder of ``flow_label`` under ``reports`` cut while a run of the config ``digest`` wrote
    it, or None."""
    if not reports.is_dir():
        return None
    for folder in sorted(reports.glob(f"{flow_label}-*"), reverse=True):
        marker = folder / INCOMPLETE
        if marker.is_file() and marker.read_text().split("\n", 1)[0] == digest:
            return folder
    return None


@contextlib.contextmanager
def writing_report(report_dir: Path, digest: str) -> Iterator[None]:
    """Within: ``report_dir`` holds the marker (first line: the config's digest) and a stop says so; removed when
    the block ends without an error."""
    from flows.lifecycle import report_writing

    report_dir.mkdir(parents=True, exist_ok=True)
    marker = report_dir / INCOMPLETE
    marker.write_text(f"{digest}\nThis report was cut while it was written (the run was stopped or failed): run the "
                      "same command again to rewrite it.\n")
    report_writing(report_dir)
    try:
        yield
    finally:
        report_writing(None)
    marker.unlink(missing_ok=True)
