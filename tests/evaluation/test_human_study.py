"""Tests of the human evaluation kit (tasks/evaluation/human_study.py, paper sec. 4.1.3).

The questionnaire is answered in a real headless Chromium driven over the Chrome DevTools protocol
(``--remote-debugging-pipe``): the test clicks the radio buttons and the download button, and Chromium saves the
Blob download; read_answers() must return the scripted scores unblinded.
"""
from __future__ import annotations

import fcntl
import json
import math
import os
import shutil
import subprocess
import time
from pathlib import Path

import av
import numpy as np
import pandas as pd
import pytest
from scipy import stats

from tasks.evaluation.human_study import (
    CSV_COLUMNS,
    QUESTIONS,
    HumanStudyError,
    analyse,
    read_answers,
    write_questionnaire,
)

METHODS = ("full_virsqueezer", "wo_dirichlet", "text_only_generation")
OBJECTS = ("tomato", "paper cup, large")  # a comma and a space survive the CSV round trip
CHROMIUM = os.environ.get("VIRSQUEEZER_CHROMIUM", "/usr/bin/chromium")


def _mp4(path: Path, shade: int, n_frames: int = 6) -> Path:
    """A tiny H.264 MP4 (32x32, 12 fps) of a flat grey ``shade`` with a moving white bar."""
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=12)
        stream.width, stream.height, stream.pix_fmt = 32, 32, "yuv420p"
        for t in range(n_frames):
            img = np.full((32, 32, 3), shade, np.uint8)
            img[:, 4 * t:4 * t + 4] = 255
            container.mux(stream.encode(av.VideoFrame.from_ndarray(img, format="rgb24")))
        container.mux(stream.encode())
    return path


@pytest.fixture(scope="module")
def items(tmp_path_factory):
    folder = tmp_path_factory.mktemp("videos")
    return [(obj, m, _mp4(folder / f"{i}_{m}.mp4", 40 * (i + 1) + 10 * j))
            for i, obj in enumerate(OBJECTS) for j, m in enumerate(METHODS)]


# ----------------------------------------------------------------------------------------------- analysis
def _ratings(rows):
    return pd.DataFrame(rows, columns=["participant", "object", "method", "question", "score"])


def test_analyse_known_means_sd_and_paired_tests():
    # two participants x two objects = 4 pairs; full always 5, base 4, 3, 2, 1: differences 1, 2, 3, 4
    pairs = [("p1", "can"), ("p1", "duck"), ("p2", "can"), ("p2", "duck")]
    rows = [(p, o, "full", "visual_quality", 5) for p, o in pairs]
    rows += [(p, o, "base", "visual_quality", s) for (p, o), s in zip(pairs, [4, 3, 2, 1])]
    rows += [("p1", "can", "lonely", "visual_quality", 3)]  # one pair only
    rows += [(p, o, m, "motion_realism", 4) for p, o in pairs for m in ("full", "base")]  # no difference
    rows += [(p, o, "full", "motion_consistency", 4) for p, o in pairs]
    rows += [(p, o, "base", "motion_consistency", 3) for p, o in pairs]  # constant difference -1
    out = analyse(_ratings(rows), "full").set_index(["method", "question"])
    assert list(out.index.get_level_values(0)[:1]) == ["full"]  # reference first
    ref = out.loc[("full", "visual_quality")]
    assert (ref["mean"], ref["sd"], ref["n"]) == (5.0, 0.0, 4) and ref["note"] == "reference method"
    assert math.isnan(ref["p_wilcoxon"]) and math.isnan(ref["p_ttest"])
    base = out.loc[("base", "visual_quality")]
    assert base["mean"] == 2.5 and base["sd"] == pytest.approx(math.sqrt(5 / 3)) and base["n"] == 4
    assert base["n_pairs"] == 4 and base["mean_diff"] == -2.5
    # exact Wilcoxon: all four differences have one sign -> two-sided p = 2 / 2^4
    assert base["p_wilcoxon"] == pytest.approx(0.125)
    # paired t: t = mean(d) / (sd(d) / sqrt(n)) = 2.5 / (sqrt(5/3) / 2), 3 degrees of freedom
    t = 2.5 / (math.sqrt(5 / 3) / 2)
    assert base["p_ttest"] == pytest.approx(2 * stats.t.sf(t, 3)) and base["note"] == ""
    lonely = out.loc[("lonely", "visual_quality")]
    assert lonely["n_pairs"] == 1 and math.isnan(lonely["sd"]) and math.isnan(lonely["p_wilcoxon"])
    assert lonely["note"] == "1 pair(s) with the reference: need >= 2"
    same = out.loc[("base", "motion_realism")]
    assert same["mean_diff"] == 0 and math.isnan(same["p_ttest"]) and same["note"] == "all paired differences are zero"
    const = out.loc[("base", "motion_consistency")]
    assert const["p_wilcoxon"] == pytest.approx(0.125) and math.isnan(const["p_ttest"])
    assert "constant" in const["note"]
    with pytest.raises(HumanStudyError, match="reference method 'nope' has no ratings"):
        analyse(_ratings(rows), "nope")


# ----------------------------------------------------------------------------------------------- blinding
def test_questionnaire_is_blinded_and_deterministic(items, tmp_path):
    page = write_questionnaire(items, tmp_path / "a", seed=7)
    text = page.read_text()
    key = json.loads((tmp_path / "a" / "key.json").read_text())
    assert not any(m in text for m in METHODS)  # nor in the embedded videos
    assert not any(Path(p).name in text for _, _, p in items)
    assert text.count("<video") == len(items) and "http://" not in text and "https://" not in text
    assert "default-src 'none'" in text  # the page may not load anything
    for obj in OBJECTS:
        assert sorted(key["objects"][obj]) == ["A", "B", "C"]
        assert sorted(v["method"] for v in key["objects"][obj].values()) == sorted(METHODS)
    # same seed: identical files; another seed: another order for some object
    write_questionnaire(items, tmp_path / "b", seed=7)
    assert (tmp_path / "b" / "questionnaire.html").read_bytes() == page.read_bytes()
    assert (tmp_path / "b" / "key.json").read_bytes() == (tmp_path / "a" / "key.json").read_bytes()
    orders = set()
    for seed in range(6):
        write_questionnaire(items, tmp_path / "c", seed=seed)
        k = json.loads((tmp_path / "c" / "key.json").read_text())
        orders.add(json.dumps([[k["objects"][o][lab]["method"] for lab in "ABC"] for o in OBJECTS]))
    assert len(orders) > 1
    # a method name that would show on the page is refused
    with pytest.raises(HumanStudyError, match="appear in the questionnaire text"):
        write_questionnaire([("tomato", "tomato", items[0][2]), ("tomato", "b", items[1][2])], tmp_path / "d", 1)
    with pytest.raises(HumanStudyError, match="is not an existing .mp4"):
        write_questionnaire([("tomato", "a", tmp_path / "a" / "key.json")], tmp_path / "d", 1)


# ----------------------------------------------------------------------------------------------- browser
class _Chromium:
    """Headless Chromium driven over the DevTools protocol on a pipe (fd 3: commands in, fd 4: replies out)."""

    def __init__(self, profile: Path) -> None:
        cmd_r, self._cmd_w = os.pipe()
        self._out_r, out_w = os.pipe()

        def child_fds() -> None:  # the pipe ends become fds 3 and 4 (through fds >= 10: they may be 3 or 4 now)
            high = [fcntl.fcntl(fd, fcntl.F_DUPFD, 10) for fd in (cmd_r, out_w)]
            for fd, target in zip(high, (3, 4)):
                os.dup2(fd, target)  # inheritable; every other fd Python opened is not (PEP 446)

        self.proc = subprocess.Popen(
            [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--remote-debugging-pipe",
             f"--user-data-dir={profile}", "--no-first-run", "--autoplay-policy=no-user-gesture-required",
             "about:blank"], preexec_fn=child_fds, close_fds=False,
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        os.close(cmd_r)
        os.close(out_w)
        self._buf, self._id, self.events = b"", 0, []

    def send(self, method: str, params: dict | None = None, session: str | None = None, timeout: float = 20.0):
        self._id += 1
        msg = {"id": self._id, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = session
        os.write(self._cmd_w, json.dumps(msg).encode() + b"\0")
        reply = self._wait(lambda m: m.get("id") == self._id, timeout)
        if "error" in reply:
            raise RuntimeError(f"{method}: {reply['error']}")
        return reply["result"]

    def evaluate(self, session: str, expression: str):
        res = self.send("Runtime.evaluate", {"expression": expression, "returnByValue": True,
                                             "awaitPromise": True}, session)
        if "exceptionDetails" in res:
            raise RuntimeError(f"page script failed: {res['exceptionDetails']}")
        return res["result"].get("value")

    def wait_event(self, method: str, pred=lambda p: True, timeout: float = 20.0) -> dict:
        for ev in self.events:
            if ev.get("method") == method and pred(ev["params"]):
                self.events.remove(ev)
                return ev["params"]
        return self._wait(lambda m: m.get("method") == method and pred(m["params"]), timeout, keep=False)["params"]

    def _wait(self, match, timeout: float, keep: bool = True) -> dict:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            while b"\0" in self._buf:
                raw, self._buf = self._buf.split(b"\0", 1)
                msg = json.loads(raw)
                if match(msg):
                    return msg
                if "method" in msg:
                    self.events.append(msg)
            chunk = os.read(self._out_r, 1 << 16)
            if not chunk:
                raise RuntimeError("Chromium closed the DevTools pipe")
            self._buf += chunk
        raise TimeoutError("no DevTools reply in time")

    def close(self) -> None:
        try:
            os.write(self._cmd_w, json.dumps({"id": 0, "method": "Browser.close"}).encode() + b"\0")
            self.proc.wait(timeout=10)
        except (OSError, subprocess.TimeoutExpired):
            self.proc.kill()
            self.proc.wait()
        os.close(self._cmd_w)
        os.close(self._out_r)


def _scripted_score(obj: str, label: str, question: str) -> int:
    return 1 + (OBJECTS.index(obj) * 7 + "ABC".index(label) * 3 + QUESTIONS.index(question)) % 5


@pytest.mark.skipif(not (Path(CHROMIUM).exists() and shutil.which(CHROMIUM)),
                    reason=f"no Chromium at {CHROMIUM} (Debian: apt-get install chromium; or set VIRSQUEEZER_CHROMIUM)")
def test_headless_chromium_answers_round_trip(items, tmp_path):
    page = write_questionnaire(items, tmp_path / "study", seed=3)
    key = json.loads((tmp_path / "study" / "key.json").read_text())
    downloads = tmp_path / "downloads"
    downloads.mkdir()
    browser = _Chromium(tmp_path / "profile")
    try:
        # 1. open the questionnaire with downloads allowed into a known folder
        browser.send("Browser.setDownloadBehavior", {"behavior": "allowAndName", "downloadPath": str(downloads),
                                                     "eventsEnabled": True})
        target = browser.send("Target.createTarget", {"url": page.as_uri()})["targetId"]
        session = browser.send("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        deadline = time.monotonic() + 20
        loaded = "document.readyState === 'complete' && location.protocol === 'file:'"
        while not browser.evaluate(session, loaded):
            assert time.monotonic() < deadline, "the questionnaire did not load"
            time.sleep(0.05)
        # the embedded H.264 videos decode in the browser (their duration is known: 6 frames at 12 fps)
        durations = browser.evaluate(session, """Promise.all([...document.querySelectorAll('video')].map(v =>
            v.readyState >= 1 ? v.duration : new Promise((ok, bad) => {
              v.addEventListener('loadedmetadata', () => ok(v.duration));
              v.addEventListener('error', () => ok(-1)); })))""")
        assert len(durations) == len(items) and all(d == pytest.approx(0.5, abs=0.05) for d in durations)
        # 2. without a participant id, nothing is saved
        browser.evaluate(session, "document.getElementById('download').click()")
        assert "participant ID" in browser.evaluate(session, "document.getElementById('status').textContent")
        # 3. scripted answers (one question left out), participant id, download
        skipped = (OBJECTS[1], "B", "motion_realism")
        clicks = [(o, lab, q, _scripted_score(o, lab, q)) for o in OBJECTS for lab in "ABC" for q in QUESTIONS
                  if (o, lab, q) != skipped]
        clicked = browser.evaluate(session, f"""(() => {{ let n = 0;
            for (const [o, l, q, s] of {json.dumps(clicks)}) {{
              for (const fs of document.querySelectorAll('fieldset.q'))
                if (fs.dataset.object === o && fs.dataset.label === l && fs.dataset.question === q) {{
                  fs.querySelector('input[value="' + s + '"]').click(); n++; }} }}
            const p = document.getElementById('participant'); p.value = 'P07, "test"';
            document.getElementById('download').click(); return n; }})()""")
        assert clicked == len(clicks)
        begin = browser.wait_event("Browser.downloadWillBegin")
        assert begin["suggestedFilename"] == "answers-P07_test_.csv"
        browser.wait_event("Browser.downloadProgress",
                           lambda p: p["guid"] == begin["guid"] and p["state"] == "completed")
        status = browser.evaluate(session, "document.getElementById('status').textContent")
        assert status == f"Saved {len(clicks)} answers; 1 questions are still unanswered."
    finally:
        browser.close()
    # 4. the saved CSV unblinds to the scripted scores
    saved = downloads / begin["guid"]
    raw = pd.read_csv(saved, dtype=str, keep_default_na=False)
    assert tuple(raw.columns) == CSV_COLUMNS and set(raw["questionnaire"]) == {key["questionnaire"]}
    answers = read_answers([saved, saved], tmp_path / "study" / "key.json")  # a repeated file counts once
    expected = pd.DataFrame(
        [('P07, "test"', o, key["objects"][o][lab]["method"], q, s) for o, lab, q, s in clicks],
        columns=["participant", "object", "method", "question", "score"]).astype({"score": "int64"})
    cell = ["participant", "object", "method", "question"]
    pd.testing.assert_frame_equal(answers, expected.sort_values(cell, ignore_index=True))
    # a CSV of another questionnaire is refused with the wrong key
    write_questionnaire(items, tmp_path / "other", seed=4)
    with pytest.raises(HumanStudyError, match="use the key.json written next to that questionnaire"):
        read_answers([saved], tmp_path / "other" / "key.json")
