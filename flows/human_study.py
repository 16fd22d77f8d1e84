"""The human evaluation of paper sec. 4.1.3 (Table 1's human columns), from a finished run's report folder.

    python -m flows.human_study build reports/evaluate-<time>                    # questionnaire.html + key.json
    python -m flows.human_study analyse reports/evaluate-<time> answers/*.csv    # human_study.csv, printed table

``build`` writes ``<report>/human_study/questionnaire.html`` (self-contained; the videos of every object and
method in a randomised, blinded order, three 1-5 questions each; participants download their answers as CSV)
and ``key.json`` (which label is which method; keep it away from participants).  The methods are the report's
final videos per variant (``<object>_<variant>_final.mp4``).  ``analyse`` unblinds the CSVs with the key and
writes mean, standard deviation and paired tests against the reference method to ``human_study.csv``.
No computation lives here: :mod:`tasks.evaluation.human_study` does it.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from tasks.evaluation.human_study import HumanStudyError, analyse, read_answers, write_questionnaire


def study_items(report: Path, variants: list[str]) -> list[tuple[str, str, Path]]:
    """(object, method, video) for every final video of the report whose variant is in ``variants``."""
    items = []
    for video in sorted(report.glob("*_final.mp4")):
        for variant in variants:
            suffix = f"_{variant}_final.mp4"
            if video.name.endswith(suffix):
                items.append((video.name[: -len(suffix)], variant, video))
    return items


def check_inputs(command: str, report: Path, answers: list[Path]) -> None:
    """One line (``SystemExit``) naming a missing input and the fix, before anything is read or written."""
    if not report.is_dir():
        raise SystemExit(f"input error: report folder {report} does not exist: give a run's report folder "
                         f"(reports/evaluate-<time>)")
    if command != "analyse":
        return
    if not answers:
        raise SystemExit("analyse needs the participants' answer CSVs: python -m flows.human_study analyse REPORT a.csv")
    key = report / "human_study" / "key.json"
    if not key.is_file():
        raise SystemExit(f"input error: {key} does not exist: analyse the report folder whose questionnaire was built "
                         f"(python -m flows.human_study build {report})")
    missing = [str(p) for p in answers if not p.is_file()]
    if missing:
        raise SystemExit(f"input error: answer file(s) not found: {', '.join(missing[:3])}"
                         f"{f' (+{len(missing) - 3} more)' if len(missing) > 3 else ''}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("command", choices=("build", "analyse"))
    ap.add_argument("report", type=Path, help="a run's report folder")
    ap.add_argument("answers", nargs="*", type=Path, help="answer CSVs downloaded by participants (analyse)")
    ap.add_argument("--variants", default="full,no_dirichlet", help="methods compared (comma-separated variants)")
    ap.add_argument("--reference", default="full", help="method the others are tested against (analyse)")
    ap.add_argument("--seed", type=int, default=0, help="randomisation seed of the questionnaire (build)")
    a = ap.parse_args(argv)
    check_inputs(a.command, a.report, a.answers)
    out = a.report / "human_study"
    if a.command == "build":
        items = study_items(a.report, a.variants.split(","))
        if not items:
            raise SystemExit(f"no final videos (*_<variant>_final.mp4) in {a.report}: give a run's report folder")
        path = write_questionnaire(items, out, a.seed)
        print(f"questionnaire: {path} ({len(items)} videos); key: {out / 'key.json'} (keep it from participants)")
        return
    try:
        table = analyse(read_answers(a.answers, out / "key.json"), a.reference)
    except HumanStudyError as exc:
        raise SystemExit(f"input error: {exc}") from None
    table.to_csv(out / "human_study.csv", index=False)
    print(table.to_string(index=False))
    print(f"written: {out / 'human_study.csv'}")


if __name__ == "__main__":
    main()
