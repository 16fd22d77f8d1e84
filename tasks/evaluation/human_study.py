"""Human evaluation kit (paper sec. 4.1.3, "Human Evaluation"; Table 1's human-evaluation columns).

As in the paper (following PhysGen3D and PhysDreamer), participants watch each object's videos from every method
in a randomised order and rate visual quality, motion realism and motion consistency (the alignment of the
effect with the squeezing) on a 5-point Likert scale (1 = worst, 5 = best).

* :func:`write_questionnaire` writes ONE self-contained HTML file (videos embedded as base64 ``data:`` URIs,
  a Content-Security-Policy that forbids every network request) in which each object's videos carry blinded
  labels A, B, C, ... in a seeded random order; the label -> method key goes to ``key.json`` next to it, never
  into the HTML.  The participant enters an ID and presses "Download answers", which saves
  ``answers-<participant>.csv`` (a Blob download) with the columns of :data:`CSV_COLUMNS`:

  ``questionnaire`` (id of the questionnaire, checked against ``key.json``), ``participant`` (the ID typed in),
  ``object``, ``label`` (A, B, ...), ``question`` (one of :data:`QUESTIONS`), ``score`` (integer 1-5);
  one row per answered question, unanswered questions are left out.
* :func:`read_answers` reads such CSV files and unblinds them with ``key.json``; :func:`analyse` reports mean,
  standard deviation and paired tests (Wilcoxon signed-rank, paired t) of every method against the reference.
"""
from __future__ import annotations

import base64
import hashlib
import html
import json
import math
import re
import string
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Optional, Union

import numpy as np
import pandas as pd
from scipy import stats

QUESTIONS: tuple[str, ...] = ("visual_quality", "motion_realism", "motion_consistency")
QUESTION_TEXT: dict[str, str] = {
    "visual_quality": "Visual quality: how sharp, clean and free of artefacts does the video look?",
    "motion_realism": "Motion realism: how physically realistic are the object's deformation and any material "
                      "it releases?",
    "motion_consistency": "Motion consistency: how well do the deformation and effect follow the squeezing "
                          "(which fingers press, when, how strongly)?",
}
CSV_COLUMNS: tuple[str, ...] = ("questionnaire", "participant", "object", "label", "question", "score")
KEY_FORMAT = "virsqueezer-human-study-key-v1"
LABELS = string.ascii_uppercase
_MEDIA_TYPES = {".mp4": "video/mp4", ".png": "image/png", ".jpg": "image/jpeg", ".jpeg": "image/jpeg"}

PathLike = Union[str, Path]


class HumanStudyError(ValueError):
    """Bad questionnaire input or answers; the one-line message names the input and the fix."""


def write_questionnaire(items: Sequence[tuple[str, str, PathLike]], out_dir: PathLike, seed: int,
                        controls: Optional[Mapping[str, PathLike]] = None,
                        title: str = "Squeezing effects: user study") -> Path:
    """Write the blinded questionnaire of the user study (paper sec. 4.1.3) and its key.

    items: (object, method, video path) per video; every video is an H.264 ``.mp4`` a browser can play.
    out_dir: folder receiving ``questionnaire.html`` and ``key.json``.  seed: the randomisation seed (same items
    and seed -> byte-identical files).  controls: optional object -> ``.png``/``.jpg``/``.mp4`` rendering of the
    squeezing control signals, shown above that object's videos (for the motion-consistency question).
    Object order and, per object, the order of the methods are random; labels A, B, ... follow display order.
    Returns the HTML path.  Raises :class:`HumanStudyError` on bad items or when a method name would appear in
    the page (it would unblind the study)."""
    # 1. check the items
    videos = _check_items(items)
    controls = dict(controls or {})
    unknown = sorted(set(controls) - set(videos))
    if unknown:
        raise HumanStudyError(f"controls name object(s) {', '.join(unknown)} that have no video in items")
    # 2. randomise: object order, then method order per object; labels in display order
    rng = np.random.default_rng(seed)
    objects = list(videos)
    object_order = [objects[i] for i in rng.permutation(len(objects))]
    assignment = {obj: {LABELS[k]: videos[obj][i] for k, i in enumerate(rng.permutation(len(videos[obj])))}
                  for obj in object_order}
    # 3. the key, and the questionnaire id that ties the answers to it
    key_objects = {obj: {label: {"method": m, "video": str(p), "sha256": _file_sha256(p)}
                         for label, (m, p) in labels.items()} for obj, labels in assignment.items()}
    qid = hashlib.sha256(json.dumps({"seed": int(seed), "objects": key_objects}, sort_keys=True).encode()
                         ).hexdigest()[:16]
    key = {"format": KEY_FORMAT, "questionnaire": qid, "seed": int(seed), "questions": list(QUESTIONS),
           "object_order": object_order, "objects": key_objects}
    # 4. the page; no method name may appear in it outside the embedded media
    page = _render_page(title, qid, assignment, controls)
    visible = re.sub(r"data:[a-z]+/[a-z0-9.+-]+;base64,[A-Za-z0-9+/=]*", "", page)
    leaked = sorted({m for labels in assignment.values() for m, _ in labels.values() if m in visible})
    if leaked:
        raise HumanStudyError(f"method name(s) {', '.join(map(repr, leaked))} appear in the questionnaire text "
                              "(e.g. inside an object name or the title): rename the methods to unblind-safe ids")
    # 5. write both files
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "key.json").write_text(json.dumps(key, indent=1, sort_keys=True), encoding="utf-8")
    path = out / "questionnaire.html"
    path.write_text(page, encoding="utf-8")
    return path


def read_answers(csv_paths: Iterable[PathLike], key_json: PathLike) -> pd.DataFrame:
    """The unblinded answers of the user study (paper sec. 4.1.3).

    csv_paths: files saved by the questionnaire's "Download answers" button (columns :data:`CSV_COLUMNS`).
    key_json: the ``key.json`` written next to that questionnaire.  Returns one row per rating with columns
    participant (str), object (str), method (str), question (one of :data:`QUESTIONS`), score (int64, 1-5),
    sorted.  Identical repeated rows (a participant downloading twice) count once; conflicting ones are an
    error."""
    key = json.loads(Path(key_json).read_text(encoding="utf-8"))
    if key.get("format") != KEY_FORMAT:
        raise HumanStudyError(f"{key_json} is not a questionnaire key ({KEY_FORMAT}): pass the key.json written "
                              "by write_questionnaire")
    tables = []
    for path in csv_paths:
        df = pd.read_csv(path, dtype=str, keep_default_na=False)
        if tuple(df.columns) != CSV_COLUMNS:
            raise HumanStudyError(f"{path} has columns {list(df.columns)}, expected {list(CSV_COLUMNS)}: pass the "
                                  "file saved by the questionnaire")
        wrong = sorted(set(df["questionnaire"]) - {key["questionnaire"]})
        if wrong:
            raise HumanStudyError(f"{path} answers questionnaire {wrong[0]} but {key_json} is the key of "
                                  f"{key['questionnaire']}: use the key.json written next to that questionnaire")
        tables.append(_unblind(df, key["objects"], str(path)))
    if not tables:
        raise HumanStudyError("read_answers got no CSV files: pass the answers-<participant>.csv files")
    answers = pd.concat(tables, ignore_index=True).drop_duplicates()
    cell = ["participant", "object", "method", "question"]
    clash = answers[answers.duplicated(cell, keep=False)]
    if len(clash):
        first = clash.iloc[0]
        raise HumanStudyError(f"participant {first.participant!r} gave {first.object}/{first.method}/"
                              f"{first.question} different scores in different files: keep one file per participant")
    return answers.sort_values(cell, ignore_index=True)


def analyse(df: pd.DataFrame, reference_method: str) -> pd.DataFrame:
    """Per method and question: mean, standard deviation and paired tests against the reference method (paper
    sec. 4.1.3, Table 1; "reference" = the full VirSqueezer).

    df: ratings with columns participant, object, method, question, score (as from :func:`read_answers`).
    Returns one row per (method, question), reference first, with columns method, question, mean, sd (sample
    standard deviation, ddof = 1), n (ratings), n_pairs ((participant, object) pairs rated for both this method
    and the reference; 0 for the reference itself), mean_diff (mean of method - reference over the pairs), p_wilcoxon (two-sided Wilcoxon
    signed-rank test, zero differences discarded: scipy ``zero_method="wilcox"``, exact for small samples),
    p_ttest (two-sided paired t-test) and note (why a p-value is NaN: the reference itself, fewer than 2 pairs,
    all differences zero, or constant differences for the t-test)."""
    missing = sorted({"participant", "object", "method", "question", "score"} - set(df.columns))
    if missing:
        raise HumanStudyError(f"ratings lack column(s) {', '.join(missing)}: pass the table from read_answers")
    if reference_method not in set(df["method"]):
        raise HumanStudyError(f"reference method {reference_method!r} has no ratings: choose one of "
                              f"{sorted(set(df['method']))}")
    methods = [reference_method] + sorted(set(df["method"]) - {reference_method})
    rows = []
    for question in [q for q in QUESTIONS if q in set(df["question"])]:
        table = df[df["question"] == question].pivot_table(index=["participant", "object"], columns="method",
                                                            values="score", aggfunc="mean")
        for method in methods:
            scores = df[(df["question"] == question) & (df["method"] == method)]["score"].to_numpy(float)
            if scores.size == 0:
                continue
            paired = table[[method, reference_method]].dropna()
            d = (paired[method] - paired[reference_method]).to_numpy(float)
            rows.append({"method": method, "question": question, "mean": scores.mean(),
                         "sd": scores.std(ddof=1) if scores.size > 1 else math.nan, "n": scores.size,
                         "n_pairs": 0 if method == reference_method else d.size,
                         "mean_diff": d.mean() if d.size and method != reference_method else math.nan,
                         **_paired_tests(d, method == reference_method)})
    return pd.DataFrame(rows, columns=["method", "question", "mean", "sd", "n", "n_pairs", "mean_diff",
                                       "p_wilcoxon", "p_ttest", "note"])


def _paired_tests(d: np.ndarray, is_reference: bool) -> dict[str, object]:
    """Two-sided Wilcoxon signed-rank and paired t-test p-values of the differences ``d`` (method - reference)."""
    nan = math.nan
    if is_reference:
        return {"p_wilcoxon": nan, "p_ttest": nan, "note": "reference method"}
    if d.size < 2:
        return {"p_wilcoxon": nan, "p_ttest": nan, "note": f"{d.size} pair(s) with the reference: need >= 2"}
    if np.all(d == 0):
        return {"p_wilcoxon": nan, "p_ttest": nan, "note": "all paired differences are zero"}
    p_w = float(stats.wilcoxon(d, zero_method="wilcox", alternative="two-sided").pvalue)
    if np.all(d == d[0]):
        return {"p_wilcoxon": p_w, "p_ttest": nan, "note": "constant paired differences: t-test undefined"}
    return {"p_wilcoxon": p_w, "p_ttest": float(stats.ttest_1samp(d, 0.0).pvalue), "note": ""}


def _check_items(items: Sequence[tuple[str, str, PathLike]]) -> dict[str, list[tuple[str, Path]]]:
    """object -> [(method, path)] in the order given, every video checked."""
    videos: dict[str, list[tuple[str, Path]]] = {}
    for entry in items:
        if len(entry) != 3:
            raise HumanStudyError(f"item {entry!r} must be (object, method, mp4 path)")
        obj, method, path = str(entry[0]), str(entry[1]), Path(entry[2])
        if not obj.strip() or not method.strip():
            raise HumanStudyError(f"item {entry!r} has an empty object or method name")
        if any(m == method for m, _ in videos.get(obj, [])):
            raise HumanStudyError(f"object {obj!r} lists method {method!r} twice: give one video per method")
        if path.suffix.lower() != ".mp4" or not path.is_file() or _read_head(path)[4:8] != b"ftyp":
            raise HumanStudyError(f"video {path} of {obj}/{method} is not an existing .mp4 file: encode it as H.264 "
                                  "MP4")
        videos.setdefault(obj, []).append((method, path))
    if not videos:
        raise HumanStudyError("write_questionnaire got no items: pass (object, method, mp4 path) tuples")
    crowded = [o for o, v in videos.items() if len(v) > len(LABELS)]
    if crowded:
        raise HumanStudyError(f"object {crowded[0]!r} has more than {len(LABELS)} methods: split the study")
    return videos


def _unblind(df: pd.DataFrame, key_objects: dict, source: str) -> pd.DataFrame:
    """Rows of one answer file with ``label`` replaced by ``method``, every value checked."""
    out = []
    for row in df.itertuples(index=False):
        method = key_objects.get(row.object, {}).get(row.label, {}).get("method")
        if method is None:
            raise HumanStudyError(f"{source}: object {row.object!r} label {row.label!r} is not in the key: use the "
                                  "key.json written next to that questionnaire")
        if row.question not in QUESTIONS:
            raise HumanStudyError(f"{source}: question {row.question!r} is not one of {', '.join(QUESTIONS)}")
        if row.score not in {"1", "2", "3", "4", "5"}:
            raise HumanStudyError(f"{source}: score {row.score!r} must be an integer 1-5")
        if not row.participant.strip():
            raise HumanStudyError(f"{source}: a row has an empty participant id")
        out.append((row.participant, row.object, method, row.question, int(row.score)))
    table = pd.DataFrame(out, columns=["participant", "object", "method", "question", "score"])
    return table.astype({"score": "int64"})


def _read_head(path: Path) -> bytes:
    with open(path, "rb") as f:
        return f.read(12)


def _file_sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _data_uri(path: Path) -> str:
    media = _MEDIA_TYPES.get(path.suffix.lower())
    if media is None:
        raise HumanStudyError(f"controls file {path} must be .png, .jpg or .mp4")
    return f"data:{media};base64,{base64.b64encode(path.read_bytes()).decode('ascii')}"


def _media(path: Path) -> str:
    src = _data_uri(path)
    if src.startswith("data:video/"):
        return f'<video controls loop muted playsinline preload="auto" src="{src}"></video>'
    return f'<img alt="squeezing control signals" src="{src}">'


def _render_page(title: str, qid: str, assignment: dict[str, dict[str, tuple[str, Path]]],
                 controls: Mapping[str, PathLike]) -> str:
    sections = []
    for k, (obj, labels) in enumerate(assignment.items()):
        cards = []
        for label, (_, path) in labels.items():
            questions = []
            for q in QUESTIONS:
                radios = "".join(f'<label><input type="radio" name="q-{k}-{label}-{q}" value="{s}"> {s}</label>'
                                 for s in range(1, 6))
                questions.append(f'<fieldset class="q" data-object="{html.escape(obj)}" data-label="{label}" '
                                 f'data-question="{q}"><legend>{html.escape(QUESTION_TEXT[q])}</legend>'
                                 f'<span class="scale">1 = worst</span>{radios}<span class="scale">5 = best</span>'
                                 '</fieldset>')
            cards.append(f'<div class="card"><h3>Video {label}</h3>{_media(path)}{"".join(questions)}</div>')
        ctrl = (f'<div class="controls"><h3>Squeezing controls</h3>{_media(Path(controls[obj]))}</div>'
                if obj in controls else "")
        sections.append(f'<section><h2>Object {k + 1} of {len(assignment)}: {html.escape(obj)}</h2>{ctrl}'
                        f'<div class="cards">{"".join(cards)}</div></section>')
    return _PAGE.format(title=html.escape(title), qid=qid, sections="\n".join(sections),
                        columns=",".join(CSV_COLUMNS))


_PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8">
<meta http-equiv="Content-Security-Policy" content="default-src 'none'; img-src data:; media-src data:; \
style-src 'unsafe-inline'; script-src 'unsafe-inline'">
<title>{title}</title>
<style>
body {{ font-family: sans-serif; margin: 1.5em; }} .cards {{ display: flex; flex-wrap: wrap; gap: 1em; }}
.card {{ border: 1px solid #bbb; padding: 0.5em; width: 440px; }} .card video {{ width: 100%; }}
.controls img, .controls video {{ max-width: 900px; width: 100%; }}
fieldset {{ margin: 0.4em 0; }} .scale {{ color: #666; font-size: 0.85em; margin: 0 0.4em; }}
#bar {{ position: sticky; top: 0; background: #fff; padding: 0.5em 0; border-bottom: 1px solid #ddd; }}
</style></head>
<body data-questionnaire="{qid}">
<h1>{title}</h1>
<p>Each object below was squeezed by a hand, and several videos show the result. Watch every video (they loop),
then rate it on the three questions: 1 = worst, 5 = best. The videos are in random order; their letters say
nothing about how they were made. When you are done, press "Download answers" and hand in the saved file.</p>
<div id="bar"><label>Participant ID: <input id="participant" autocomplete="off"></label>
<button id="download" type="button">Download answers</button> <span id="status" role="status"></span></div>
{sections}
<script>
"use strict";
const QUESTIONNAIRE = document.body.dataset.questionnaire;
function csvField(value) {{
  const s = String(value);
  return /[",\\r\\n]/.test(s) ? '"' + s.replace(/"/g, '""') + '"' : s;
}}
document.getElementById("download").addEventListener("click", () => {{
  const status = document.getElementById("status");
  const participant = document.getElementById("participant").value.trim();
  if (!participant) {{ status.textContent = "Please enter your participant ID first."; return; }}
  const lines = ["{columns}"];
  let missing = 0;
  for (const fs of document.querySelectorAll("fieldset.q")) {{
    const checked = fs.querySelector("input:checked");
    if (!checked) {{ missing++; continue; }}
    lines.push([QUESTIONNAIRE, participant, fs.dataset.object, fs.dataset.label, fs.dataset.question,
                checked.value].map(csvField).join(","));
  }}
  if (lines.length === 1) {{ status.textContent = "No answers yet."; return; }}
  const link = document.createElement("a");
  link.href = URL.createObjectURL(new Blob([lines.join("\\n") + "\\n"], {{type: "text/csv"}}));
  link.download = "answers-" + participant.replace(/[^A-Za-z0-9_-]+/g, "_") + ".csv";
  document.body.appendChild(link);
  link.click();
  link.remove();
  setTimeout(() => URL.revokeObjectURL(link.href), 60000);
  status.textContent = "Saved " + (lines.length - 1) + " answers" +
    (missing ? "; " + missing + " questions are still unanswered." : ".");
}});
</script>
</body></html>
"""
