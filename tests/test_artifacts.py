"""Zarr artifacts: labelled arrays, content digests, atomic writes, incomplete groups never valid."""
import json

import numpy as np
import pytest
import zarr

from tasks.core.artifacts import Array, ArtifactError, content_digest, read_artifact, read_group_attrs, write_artifact


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
