"""Zarr artifacts: labelled arrays, content digests, atomic writes, incomplete or damaged groups never valid,
chunk sizes, references relative to the artifacts root, stale temporaries."""
import json
from pathlib import Path

import numpy as np
import pytest
import zarr

from tasks.core.artifacts import (
    FORMAT_VERSION,
    Array,
    ArtifactDamaged,
    ArtifactError,
    ArtifactOutdated,
    ArtifactRef,
    chunk_shape,
    content_digest,
    read_artifact,
    read_group_attrs,
    remove_stale_temporaries,
    scratch_name,
    verify_artifact,
    write_artifact,
)


def _arrays(scale=1.0):
    return {
        "force_coefficients": Array(np.arange(10, dtype=np.float32).reshape(2, 5) * scale, ("frame", "finger"), "1"),
        "time": Array(np.array([0.0, 1 / 30]), ("frame",), "s"),
    }


def test_round_trip_labels_units_and_digest(tmp_path):
    ref = write_artifact(tmp_path / "a.zarr", _arrays(), step="force_coefficients", scope="can",
                         config_digest="cfg123", attrs={"frame_rate": 30.0})
    art = read_artifact(ref)
    np.testing.assert_array_equal(art["force_coefficients"], _arrays()["force_coefficients"].data)
    assert art.dims["force_coefficients"] == ["frame", "finger"]
    assert art.units["time"] == "s"
    assert art.attrs == {"frame_rate": 30.0}
    group = zarr.open_group(ref.path, mode="r")
    assert group["time"].attrs["config_digest"] == "cfg123"
    assert group["time"].metadata.dimension_names == ("frame",)
    assert group.attrs["complete"] is True and group.attrs["digest"] == ref.digest
    assert ref.digest == content_digest(_arrays(), {"frame_rate": 30.0})


def test_digest_changes_with_content_units_and_labels():
    base = content_digest(_arrays(), {})
    assert content_digest(_arrays(2.0), {}) != base
    other_units = dict(_arrays(), time=Array(np.array([0.0, 1 / 30]), ("frame",), "ms"))
    assert content_digest(other_units, {}) != base
    other_dims = dict(_arrays(), time=Array(np.array([0.0, 1 / 30]), ("sample",), "s"))
    assert content_digest(other_dims, {}) != base
    assert content_digest(_arrays(), {}) == base  # deterministic


def test_incomplete_group_is_never_valid(tmp_path):
    ref = write_artifact(tmp_path / "a.zarr", _arrays(), step="s", scope="o", config_digest="c")
    meta = tmp_path / "a.zarr" / "zarr.json"
    doc = json.loads(meta.read_text())
    del doc["attributes"]["complete"]  # what an interrupted writer would leave
    meta.write_text(json.dumps(doc))
    with pytest.raises(ArtifactError, match="incomplete"):
        read_group_attrs(ref.path)
    with pytest.raises(ArtifactError):
        read_artifact(ref)
    assert not ref.exists()


def test_rewritten_artifact_is_detected(tmp_path):
    ref = write_artifact(tmp_path / "a.zarr", _arrays(), step="s", scope="o", config_digest="c")
    write_artifact(tmp_path / "a.zarr", _arrays(3.0), step="s", scope="o", config_digest="c")
    with pytest.raises(ArtifactError, match="expected"):
        read_artifact(ref)


def test_no_temporary_left_and_missing_is_clear(tmp_path):
    write_artifact(tmp_path / "a.zarr", _arrays(), step="s", scope="o", config_digest="c")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.zarr"]
    with pytest.raises(ArtifactError, match="missing"):
        read_group_attrs(tmp_path / "nothing.zarr")


def test_dimension_names_must_match_rank():
    with pytest.raises(ValueError, match="dimension names"):
        Array(np.zeros((2, 3)), ("frame",), "1")


def test_concurrent_writers_of_the_same_artifact_all_succeed(tmp_path):
    """Two runs on one artifacts folder compute the same step at once: every writer returns the reference of
    the one complete group in place, none fails on the directory rename, no temporary or trash is left."""
    import threading

    writers, errors, refs = 4, [], []
    for trial in range(15):
        path = tmp_path / f"t{trial}.zarr"
        start = threading.Barrier(writers)

        def write(path=path, start=start):
            start.wait()
            try:
                refs.append(write_artifact(path, _arrays(), step="s", scope="o", config_digest="c"))
            except Exception as exc:  # noqa: BLE001 - collected and asserted below
                errors.append(repr(exc))

        threads = [threading.Thread(target=write) for _ in range(writers)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert read_group_attrs(path)["digest"] == refs[-1].digest
    assert errors == []
    assert len(refs) == 15 * writers and len({r.digest for r in refs}) == 1
    assert all(read_artifact(r)["time"][1] == 1 / 30 for r in refs)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(f"t{i}.zarr" for i in range(15))


# ------------------------------------------------------------------------------------------- integrity (format 2)
def _big(frames=3):
    """A 24 MiB array chunked along its leading axis (16 MiB target: two frames per chunk) and a small one."""
    data = np.arange(frames * 1024 * 1024, dtype=np.float64).reshape(frames, 1024, 1024) % 977.0
    return {"field": Array(data, ("frame", "point", "xyz"), "m"),
            "time": Array(np.arange(frames) / 30.0, ("frame",), "s")}


def test_every_file_but_the_root_metadata_is_in_the_manifest(tmp_path):
    import hashlib
    import os

    ref = write_artifact(tmp_path / "a.zarr", _big(), step="s", scope="o", config_digest="c")
    attrs = verify_artifact(ref.path)
    files = sorted(str(p.relative_to(ref.path)) for p in Path(ref.path).rglob("*") if p.is_file())
    assert sorted(attrs["manifest"]) == [f for f in files if f != "zarr.json"]
    assert "field/c/1/0/0" in attrs["manifest"] and "field/zarr.json" in attrs["manifest"]
    for name, (size, sha) in attrs["manifest"].items():
        data = (Path(ref.path) / name).read_bytes()
        assert size == os.path.getsize(Path(ref.path) / name) and sha == hashlib.sha256(data).hexdigest()
    assert attrs["format_version"] == FORMAT_VERSION == 2


def _delete(group: Path) -> str:
    (group / "field" / "c" / "1" / "0" / "0").unlink()
    return "missing file field/c/1/0/0"


def _truncate(group: Path) -> str:
    chunk = group / "field" / "c" / "1" / "0" / "0"
    size = chunk.stat().st_size
    chunk.write_bytes(chunk.read_bytes()[: size // 2])
    return f"size mismatch of field/c/1/0/0: {size // 2} bytes, written {size}"


def _flip(group: Path) -> str:
    chunk = group / "field" / "c" / "0" / "0" / "0"
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0x01
    chunk.write_bytes(bytes(data))
    return "checksum mismatch of field/c/0/0/0"


def _array_metadata(group: Path) -> str:
    meta = group / "time" / "zarr.json"
    text = meta.read_text()
    assert '"units": "s"' in text
    meta.write_text(text.replace('"units": "s"', '"units": "ms"'))
    return f"size mismatch of time/zarr.json: {len(text) + 1} bytes, written {len(text)}"


def _extra_chunk(group: Path) -> str:
    (group / "time" / "c" / "9").write_bytes(b"\0" * 8)
    return "unexpected file time/c/9 (not written with the artifact)"


def _group_attrs(group: Path) -> str:
    meta = group / "zarr.json"
    doc = json.loads(meta.read_text())
    doc["attributes"]["attrs"] = {"frame_rate": 15.0}
    meta.write_text(json.dumps(doc))
    return "group attributes in zarr.json were changed after the write"


def _unreadable(group: Path) -> str:
    meta = group / "zarr.json"
    meta.write_bytes(meta.read_bytes()[:-7])
    return "unreadable metadata zarr.json"


DAMAGE = [_delete, _truncate, _flip, _array_metadata, _extra_chunk, _group_attrs, _unreadable]


@pytest.mark.parametrize("damage", DAMAGE, ids=lambda f: f.__name__.strip("_"))
def test_a_damaged_artifact_is_refused_with_one_line_naming_it(tmp_path, damage):
    ref = write_artifact(tmp_path / "o" / "s" / "a.zarr", _big(), step="s", scope="o", config_digest="c",
                         attrs={"frame_rate": 30.0}, root=tmp_path)
    problem = damage(Path(ref.path))
    with pytest.raises(ArtifactDamaged) as found:
        verify_artifact(ref.path)
    assert found.value.problem == problem
    with pytest.raises(ArtifactError) as exc:
        read_artifact(ref)
    assert str(exc.value) == f"input o/s: artifact {ref.path} is damaged ({problem}); rerun the flow to recompute it"
    if damage is _flip:  # the cheap size check does not see it, the checksum does
        verify_artifact(ref.path, checksums=False)


def test_a_reader_of_some_arrays_checks_their_files_only(tmp_path):
    ref = write_artifact(tmp_path / "a.zarr", _big(), step="s", scope="o", config_digest="c")
    _delete(Path(ref.path))
    assert read_artifact(ref, names=["time"])["time"][1] == 1 / 30
    assert read_artifact(ref, names=[]).arrays == {}
    with pytest.raises(ArtifactError, match="missing file field/c/1/0/0"):
        read_artifact(ref, names=["field"])


def test_an_artifact_of_the_previous_format_is_not_valid(tmp_path):
    """Format 1 had no manifest: such a group is refused (its step recomputes), never read unchecked."""
    ref = write_artifact(tmp_path / "a.zarr", _arrays(), step="s", scope="o", config_digest="c")
    meta = Path(ref.path) / "zarr.json"
    doc = json.loads(meta.read_text())
    doc["attributes"]["format_version"] = 1
    for key in ("manifest", "seal"):
        del doc["attributes"][key]
    meta.write_text(json.dumps(doc))
    with pytest.raises(ArtifactOutdated, match="written in artifact format 1, this code reads format 2"):
        read_group_attrs(ref.path)
    again = write_artifact(tmp_path / "a.zarr", _arrays(), step="s", scope="o", config_digest="c")
    assert again.digest == ref.digest and verify_artifact(again.path)["format_version"] == 2  # replaced, not kept


def test_big_arrays_are_chunked_in_blocks_of_frames(tmp_path):
    """About 100 MB in 16 MiB chunks along the frame axis: 7 chunk files, not one per frame."""
    frames = 400
    data = (np.arange(frames * 32768, dtype=np.float64).reshape(frames, 32768) % 1013.0)  # 262 kB per frame
    assert data.nbytes == 104_857_600
    ref = write_artifact(tmp_path / "a.zarr", {"x": Array(data, ("frame", "point"), "m")}, step="s", scope="o",
                         config_digest="c")
    chunks = list((Path(ref.path) / "x" / "c").rglob("*"))
    assert len([c for c in chunks if c.is_file()]) == 7
    np.testing.assert_array_equal(read_artifact(ref)["x"], data)
    assert chunk_shape((frames, 32768), 8) == (64, 32768)
    assert chunk_shape((3, 5), 8) == (3, 5) and chunk_shape((), 8) == ()
    assert chunk_shape((2, 4096, 1024), 8) == (1, 2048, 1024)  # a 32 MiB frame is split along its own axis


# ------------------------------------------------------------------------------------ references, temporaries
def test_a_reference_holds_no_absolute_path_and_is_rooted_by_its_reader(tmp_path):
    ref = write_artifact(tmp_path / "o" / "s" / "a.zarr", _arrays(), step="s", scope="o", config_digest="c",
                         root=tmp_path)
    assert ref.rel == "o/s/a.zarr" and ref.path == str(tmp_path.resolve() / "o" / "s" / "a.zarr")
    record = ref.model_dump(mode="json")
    assert str(tmp_path) not in json.dumps(record)
    loaded = ArtifactRef.model_validate(record)
    with pytest.raises(ArtifactError, match="is not rooted at an artifacts folder"):
        loaded.path
    moved = tmp_path / "elsewhere"
    (moved / "o").mkdir(parents=True)
    (tmp_path / "o" / "s").rename(moved / "o" / "s")
    assert read_artifact(loaded.at(moved))["time"][1] == 1 / 30
    for bad in ("/abs/a.zarr", "../a.zarr", "o/../../a.zarr"):
        with pytest.raises(ValueError, match="must be relative to the artifacts root"):
            ArtifactRef.model_validate(dict(record, rel=bad))
    with pytest.raises(ValueError):
        ArtifactRef.model_validate(dict(record, root=str(tmp_path)))  # a record cannot carry a root


def _dead_pid() -> int:
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_stale_temporaries_of_dead_processes_are_removed_and_live_ones_kept(tmp_path):
    import os

    step = tmp_path / "obj" / "step"
    step.mkdir(parents=True)
    mine = scratch_name(step / "k.zarr", "tmp")
    assert mine.name.startswith(".k.zarr.tmp-") and f"-{os.getpid()}-" in mine.name
    dead = mine.with_name(mine.name.replace(f"-{os.getpid()}-", f"-{_dead_pid()}-"))
    trash = scratch_name(step / "j.zarr", "trash")
    dead_trash = trash.with_name(trash.name.replace(f"-{os.getpid()}-", f"-{_dead_pid()}-"))
    legacy = step / ".old.zarr.tmp-0123456789ab"  # format 1: no owner in the name
    other_host = step / f".k.zarr.tmp-otherhost-{_dead_pid()}-0123456789ab"
    for d in (mine, dead, dead_trash, legacy, other_host):
        (d / "x").mkdir(parents=True)
        (d / "x" / "0").write_bytes(b"1" * 1000)
    write_artifact(step / "k.zarr", _arrays(), step="step", scope="obj", config_digest="c")
    assert remove_stale_temporaries(tmp_path) == (3, 3000)
    assert sorted(p.name for p in step.iterdir()) == sorted([mine.name, other_host.name, "k.zarr"])
    assert remove_stale_temporaries(tmp_path / "not-there") == (0, 0)


def test_a_cache_record_cut_by_a_kill_leaves_a_temporary_the_next_start_removes(tmp_path):
    """A step's cache record is written under a temporary name and renamed (tasks.core.records); a run killed
    between the two leaves the temporary file in ``.prefect/results``, named for its dead process: the next
    start removes it, and keeps a live writer's and the records themselves."""
    import os

    from prefect.filesystems import LocalFileSystem

    from tasks.core.records import write_replacing

    results = tmp_path / ".prefect" / "results"
    storage = LocalFileSystem(basepath=str(results))
    write_replacing(storage, "abc123", b"record")
    assert [p.name for p in results.iterdir()] == ["abc123"]  # the temporary was renamed over the record
    mine = scratch_name(results / "def456", "tmp")
    dead = mine.with_name(mine.name.replace(f"-{os.getpid()}-", f"-{_dead_pid()}-"))
    for f in (mine, dead):
        f.write_bytes(b"1" * 700)
    assert remove_stale_temporaries(tmp_path) == (1, 700)
    assert sorted(p.name for p in results.iterdir()) == sorted(["abc123", mine.name])
    assert (results / "abc123").read_bytes() == b"record"


def test_a_temporary_whose_pid_was_reused_is_removed(tmp_path):
    """The name records the process's start time with its pid: a folder named for a live pid whose process
    started at another time (the pid was reused after its writer died) is stale; the live writer's is kept."""
    import os

    from tasks.core.processes import process_started

    step = tmp_path / "obj" / "step"
    step.mkdir(parents=True)
    mine = scratch_name(step / "k.zarr", "tmp")
    started = round(1000 * process_started(os.getpid()))
    assert f"-{os.getpid()}-{started}-" in mine.name
    reused = mine.with_name(mine.name.replace(f"-{started}-", f"-{started - 3_600_000}-"))  # an hour earlier
    unstamped = mine.with_name(mine.name.replace(f"-{started}-", "-"))  # named before start times were recorded
    for d in (mine, reused, unstamped):
        (d / "x").mkdir(parents=True)
        (d / "x" / "0").write_bytes(b"1" * 1000)
    assert remove_stale_temporaries(tmp_path) == (1, 1000)
    assert sorted(p.name for p in step.iterdir()) == sorted([mine.name, unstamped.name])  # its pid is alive


def test_a_file_hashed_once_is_not_hashed_again_until_it_changes(tmp_path, monkeypatch):
    import os
    import time

    import tasks.core.artifacts as artifacts

    hashed = []
    sha256 = artifacts._file_sha256
    monkeypatch.setattr(artifacts, "_file_sha256", lambda path: hashed.append(Path(path).name) or sha256(path))
    ref = write_artifact(tmp_path / "a.zarr", _arrays(), step="s", scope="o", config_digest="c")
    files = len(verify_artifact(ref.path)["manifest"])
    hashed.clear()
    verify_artifact(ref.path)
    assert len(hashed) == files  # written just now: a change within the same clock tick would not show, so no memo
    monkeypatch.setattr(artifacts, "RACY_SECONDS", 0.0)  # as if written long ago
    verify_artifact(ref.path)
    hashed.clear()
    verify_artifact(ref.path)
    read_artifact(ref)
    assert hashed == []  # unchanged since this process hashed it
    time.sleep(0.05)  # past the file-system clock's tick
    chunk = Path(ref.path) / "time" / "c" / "0"
    before = chunk.stat()
    data = bytearray(chunk.read_bytes())
    data[0] ^= 0x01
    chunk.write_bytes(bytes(data))
    os.utime(chunk, ns=(before.st_atime_ns, before.st_mtime_ns))  # same size, mtime set back: the ctime moved
    with pytest.raises(ArtifactDamaged) as found:
        verify_artifact(ref.path)
    assert found.value.problem == "checksum mismatch of time/c/0"
    assert hashed == ["0"]
