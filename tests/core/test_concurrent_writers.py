"""Two processes racing on one cache key, repeated: the artifact (zarr group, atomic rename) and its cache record
(Prefect's record file, atomic replace) are written by both at once while a third process reads them."""
from __future__ import annotations

import json
import multiprocessing as mp
import time
from pathlib import Path

import numpy as np

ROUNDS = 50


def _arrays(i: int):
    from tasks.core.artifacts import Array

    rng = np.random.default_rng(i)  # the same content in both writers: the same step's deterministic result
    return {"x": Array(rng.random((64, 256)), ("frame", "i"), "m"), "y": Array(np.arange(i + 1), ("k",), "1")}


def _record(i: int, who: str) -> bytes:
    """A cache record as Prefect writes one (JSON), ~100 kB so that writing it takes a while; each writer's differs
    (a step computed by one and found on disk by the other)."""
    return json.dumps({"round": i, "writer": who, "pad": who * 50_000}).encode()


def _writer(who: str, root: str, barrier, out) -> None:
    from prefect.filesystems import LocalFileSystem

    import tasks.core.step  # noqa: F401 - what a flow or worker imports: Prefect's record writes made atomic
    from tasks.core.artifacts import write_artifact

    store = LocalFileSystem(basepath=str(Path(root) / ".prefect" / "results"))  # Prefect's cache record storage
    errors = []
    for i in range(ROUNDS):
        barrier.wait()
        try:
            ref = write_artifact(Path(root) / "step" / f"{i}.zarr", _arrays(i), step="step", scope="s",
                                 config_digest="c", root=root)
            store.write_path(f"key{i}", _record(i, who), _sync=True)
            out.put((who, i, ref.digest))
        except Exception as exc:  # noqa: BLE001 - counted: the test expects none
            errors.append(f"{type(exc).__name__}: {exc}")
            out.put((who, i, f"error {errors[-1]}"))
        barrier.wait()


def _reader(root: str, barrier, out) -> None:
    """Reads record and artifact of the current round while the writers write them: absent, or whole."""
    from tasks.core.artifacts import ArtifactMissing, verify_artifact

    partial = reads = 0
    for i in range(ROUNDS):
        barrier.wait()
        record, group = Path(root) / ".prefect" / "results" / f"key{i}", Path(root) / "step" / f"{i}.zarr"
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < 0.15:
            reads += 1
            try:
                doc = json.loads(record.read_bytes())
                assert doc["round"] == i
            except FileNotFoundError:
                pass
            except Exception:  # noqa: BLE001 - an empty or cut record
                partial += 1
            try:
                verify_artifact(group)
            except ArtifactMissing:
                pass
            except Exception:  # noqa: BLE001 - a group seen half-written (or whole but reported damaged)
                partial += 1
        barrier.wait()
    out.put(("reader", partial, reads))


def test_two_writers_racing_on_one_key_leave_whole_artifacts_and_records(tmp_path):
    from tasks.core.artifacts import verify_artifact

    ctx = mp.get_context("spawn")
    barrier, out = ctx.Barrier(3), ctx.Queue()
    procs = [ctx.Process(target=_writer, args=(w, str(tmp_path), barrier, out)) for w in ("a", "b")]
    procs.append(ctx.Process(target=_reader, args=(str(tmp_path), barrier, out)))
    for p in procs:
        p.start()
    results = [out.get(timeout=300) for _ in range(2 * ROUNDS + 1)]
    for p in procs:
        p.join(timeout=60)
        assert p.exitcode == 0
    (reader,) = [r for r in results if r[0] == "reader"]
    writes = [r for r in results if r[0] != "reader"]
    assert not [w for w in writes if str(w[2]).startswith("error")], writes
    for i in range(ROUNDS):
        digests = {d for _, j, d in writes if j == i}
        assert len(digests) == 1  # both writers got the one artifact's reference
        assert verify_artifact(tmp_path / "step" / f"{i}.zarr")["digest"] in digests
        doc = json.loads((tmp_path / ".prefect" / "results" / f"key{i}").read_bytes())  # no lost record
        assert doc["round"] == i and doc["writer"] in ("a", "b")
    assert reader[1] == 0, f"{reader[1]} of {reader[2]} reads saw a partial record or group"
    assert reader[2] > ROUNDS  # the reader did read during the writes
    # nothing of the writers' temporaries is left
    assert not [p for p in tmp_path.rglob("*") if ".tmp-" in p.name or ".trash-" in p.name]
