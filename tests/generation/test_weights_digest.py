"""Weight digests are remembered across runs by (path, size, mtime) and recomputed only when one of them changes
(tasks/core/digest_cache.py): the pre-flight check no longer reads ~7 GB of diffusion weights on every run, and the
cache key still carries the content digest."""
from __future__ import annotations

import hashlib
import json
import os

import pytest

from tasks.core import digest_cache
from tasks.generation.components import DiffusionWeights, weights_identity
from tests.generation.tiny_diffusion import save_diffusers_folders, tiny_components


@pytest.fixture
def store(tmp_path, monkeypatch):
    path = tmp_path / "digests.json"
    monkeypatch.setenv("VIRSQUEEZER_DIGEST_CACHE", str(path))
    monkeypatch.setattr(digest_cache, "_memory", {})
    return path


def _counting_hash(monkeypatch) -> list:
    read = []
    original = digest_cache._sha256
    monkeypatch.setattr(digest_cache, "_sha256", lambda path: read.append(path.name) or original(path))
    return read


def test_digest_is_stored_reused_by_a_new_process_and_recomputed_after_the_mtime_changes(tmp_path, store,
                                                                                          monkeypatch):
    weights = tmp_path / "w.safetensors"
    weights.write_bytes(b"a" * 1000)
    read = _counting_hash(monkeypatch)
    first = digest_cache.file_digest(weights)
    assert first == hashlib.sha256(b"a" * 1000).hexdigest() and read == ["w.safetensors"]
    status = weights.stat()
    assert json.loads(store.read_text()) == {f"{weights.resolve()}|1000|{status.st_mtime_ns}": first}
    # a new run (empty memory) reads the store, not the file
    monkeypatch.setattr(digest_cache, "_memory", {})
    assert digest_cache.file_digest(weights) == first and read == ["w.safetensors"]
    # same size, new bytes and a new mtime: hashed again, the new digest replaces the old entry
    weights.write_bytes(b"b" * 1000)
    os.utime(weights, ns=(status.st_atime_ns, status.st_mtime_ns + 10**9))
    second = digest_cache.file_digest(weights)
    assert second == hashlib.sha256(b"b" * 1000).hexdigest() != first and read == ["w.safetensors"] * 2
    assert list(json.loads(store.read_text()).values()) == [second]
    # the documented limit: new bytes of the same size with the old mtime restored are not noticed
    weights.write_bytes(b"c" * 1000)
    os.utime(weights, ns=(status.st_atime_ns, status.st_mtime_ns + 10**9))
    monkeypatch.setattr(digest_cache, "_memory", {})
    assert digest_cache.file_digest(weights) == second and len(read) == 2


def test_weights_identity_hashes_each_weight_file_once_and_follows_a_touched_file(tmp_path, store, monkeypatch):
    weights = DiffusionWeights(folder=str(tmp_path / "models"))
    save_diffusers_folders(tiny_components(seed=0), weights)
    read = _counting_hash(monkeypatch)
    identity = weights_identity(weights)
    hashed = len(read)
    assert hashed >= 7  # unet, vae, text encoder, tokenizer, motion adapter, controlnet weights...
    monkeypatch.setattr(digest_cache, "_memory", {})
    assert weights_identity(weights) == identity and len(read) == hashed  # the next run reads none of them
    unet = tmp_path / "models" / "stable-diffusion" / "unet" / "diffusion_pytorch_model.safetensors"
    data = bytearray(unet.read_bytes())
    data[-1] ^= 1
    unet.write_bytes(bytes(data))
    os.utime(unet, ns=(unet.stat().st_atime_ns, unet.stat().st_mtime_ns + 10**9))
    changed = weights_identity(weights)
    assert len(read) == hashed + 1 and read[-1] == unet.name
    assert changed["stable_diffusion"]["sha256"]["unet/diffusion_pytorch_model.safetensors"] != \
        identity["stable_diffusion"]["sha256"]["unet/diffusion_pytorch_model.safetensors"]
    assert changed["motion_adapter"] == identity["motion_adapter"]
