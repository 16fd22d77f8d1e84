"""Tests of the material oracle (tasks/physics/material_oracle.py).

The LLM backend is exercised against a REAL HTTP server on 127.0.0.1 (http.server in a thread); nothing else
is contacted.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

from conf.oracle_schema import OracleConfig
from conf.schema import MaterialOverrides
from tasks.physics.material_oracle import (
    INTERIORS,
    TABLE,
    LLMAnswer,
    MaterialOracleError,
    MaterialProperties,
    ObjectMaterials,
    match_entry,
    material_oracle,
    materials_from_dict,
    materials_to_dict,
    mpm_material_kwargs,
    oracle_for_object,
    validate_material,
)
from tests.chat_endpoint import KEY_ENV, SECRET, ChatEndpoint, assert_no_secret

ROOT = Path(__file__).resolve().parents[2]

# the eight evaluation objects: (name, description, interior) -> intended table entry
OBJECTS = {
    "can": ("an aluminium beverage can filled with carbonated cola", "cola", "aluminium_can"),
    "plush_toy": ("a plush toy with polyester stuffing", "stuffing", "plush_toy"),
    "rubber_duck": ("a hollow yellow rubber duck", None, "rubber_duck"),
    "clay": ("a block of soft modelling clay", None, "modelling_clay"),
    "tomato": ("a ripe tomato with thin skin and juicy pulp", "juice", "tomato"),
    "orange": ("an orange with thick peel and juicy segments", "juice", "orange"),
    "rubber_ball": ("a hollow rubber ball", None, "rubber_ball"),
    "paper_cup": ("a paper cup of thin paperboard", None, "paper_cup"),
}
EXPECTED_EFFECT = {"aluminium_can": "cola_spray", "plush_toy": "stuffing_spill", "rubber_duck": "rebound",
                   "modelling_clay": "dent", "tomato": "juice", "orange": "juice", "rubber_ball": "rebound",
                   "paper_cup": "buckle"}


# ----------------------------------------------------------------------------------------------- schema
def test_every_table_entry_validates():
    assert len({e.key for e in TABLE}) == len(TABLE)
    for entry in TABLE:
        assert entry.shell.source.strip() and entry.threshold_source.strip()
        again = MaterialProperties.model_validate(entry.shell.model_dump())  # re-validation round trip
        assert again == entry.shell
        interior = INTERIORS[entry.interior].material if entry.interior else None
        om = ObjectMaterials(shell=entry.shell, interior=interior, squeeze_threshold=entry.squeeze_threshold,
                             threshold_source=entry.threshold_source, effect=entry.effect,
                             matched_entry=entry.key, backend="table")
        assert materials_from_dict(json.loads(json.dumps(materials_to_dict(om)))) == om
        for m in (entry.shell, interior):
            if m is not None:
                assert 0 <= m.poisson_ratio <= 0.49 and m.youngs_modulus > 0 and m.density > 0
                assert m.wave_speed > 0
    for item in INTERIORS.values():
        assert MaterialProperties.model_validate(item.material.model_dump()) == item.material
        if item.material.model == "fluid":  # liquids: physical value, scaled by the simulator
            assert item.material.bulk_modulus == pytest.approx(2.2e9)
            assert item.material.viscosity and item.material.viscosity > 0
        if item.core is not None:  # the solid the released interior is made of: same density, not a fluid
            assert item.core.model != "fluid" and item.core.density == item.material.density
            assert item.core.source.strip()


def test_table_materials_build_mpm_materials():
    try:
        from tasks.physics.mpm.materials import material_from_dict
    except Exception as exc:  # noqa: BLE001 - the solver package is another module's work
        pytest.skip(f"tasks.physics.mpm.materials not importable: {exc}")
    mats = [e.shell for e in TABLE] + [i.material for i in INTERIORS.values()]
    for m in mats:
        mpm = material_from_dict(mpm_material_kwargs(m))
        assert mpm.p_wave_speed() == pytest.approx(m.wave_speed, rel=1e-9)
        if m.model == "fluid":
            assert mpm.bulk == pytest.approx(m.bulk_modulus)


def test_key_values_are_physical():
    can = material_oracle(*OBJECTS["can"][:1], "can", None, "cola")
    assert can.shell.youngs_modulus == pytest.approx(69e9) and can.shell.poisson_ratio == pytest.approx(0.33)
    assert 2650 <= can.shell.density <= 2750 and 250e6 <= can.shell.yield_stress <= 290e6
    assert can.interior.model == "fluid" and 1030 <= can.interior.density <= 1050
    assert can.interior.viscosity == pytest.approx(1.3e-3)
    cup = material_oracle(OBJECTS["paper_cup"][0], "paper_cup")
    assert 3e9 <= cup.shell.youngs_modulus <= 5e9 and 700 <= cup.shell.density <= 800
    assert 20e6 <= cup.shell.yield_stress <= 40e6


@pytest.mark.parametrize("name", sorted(OBJECTS))
def test_eight_objects_match_their_entries(name):
    description, interior, key = OBJECTS[name]
    assert match_entry(description, name).key == key
    assert match_entry(description).key == key  # the description alone is enough
    m = material_oracle(description, name, MaterialOverrides(), interior, OracleConfig())
    assert m.matched_entry == key and m.backend == "table" and m.effect == EXPECTED_EFFECT[key]
    if key in ("aluminium_can", "tomato", "orange", "plush_toy"):
        assert m.interior is not None and m.squeeze_threshold is not None and 0 < m.squeeze_threshold < 1
    else:
        assert m.interior is None and m.squeeze_threshold is None
    assert m == material_oracle(description, name, None, interior)  # deterministic


def test_interior_resolution():
    tomato = material_oracle(OBJECTS["tomato"][0], "tomato", None, "juice")
    orange = material_oracle(OBJECTS["orange"][0], "orange", None, "juice")
    assert tomato.interior.name.startswith("tomato") and orange.interior.name.startswith("orange")
    assert material_oracle(OBJECTS["can"][0], "can", None, "soda").interior.name == "regular cola"
    # interior None in the object config: no interior even though the entry has one
    dry = material_oracle(OBJECTS["tomato"][0], "tomato", None, None)
    assert dry.interior is None and any("dropped" in n for n in dry.notes)
    hollow = material_oracle(OBJECTS["rubber_duck"][0], "rubber_duck", None, "air")
    assert hollow.interior is None and "not simulated" in hollow.notes[0]
    with pytest.raises(MaterialOracleError, match="matches no known interior"):
        material_oracle(OBJECTS["rubber_duck"][0], "rubber_duck", None, "helium")
    with pytest.raises(MaterialOracleError, match="equally"):
        material_oracle(OBJECTS["paper_cup"][0], "paper_cup", None, "juice")  # tomato or orange juice?


def test_unmatched_description_is_a_clear_error():
    with pytest.raises(MaterialOracleError) as info:
        material_oracle("a shiny mysterious thing", "thing")
    msg = str(info.value)
    assert "\n" not in msg and "aluminium_can" in msg and "paper_cup" in msg
    assert "youngs_modulus" in msg and "backend=llm" in msg
    with pytest.raises(MaterialOracleError, match="equally"):
        material_oracle("a rubber toy", "toy")
    # explicit values make an unmatched description usable
    m = material_oracle("a shiny mysterious thing", "thing",
                        {"model": "neo_hookean", "youngs_modulus": 1e6, "poisson_ratio": 0.4, "density": 1000.0,
                         "squeeze_threshold": 0.3})
    assert m.backend == "explicit" and m.shell.youngs_modulus == 1e6 and m.squeeze_threshold == 0.3


def test_overrides_win_and_are_revalidated():
    desc, interior, _ = OBJECTS["tomato"]
    ov = MaterialOverrides(youngs_modulus=3.0e6, poisson_ratio=0.4, density=1010.0, squeeze_threshold=0.12)
    m = material_oracle(desc, "tomato", ov, interior)
    assert (m.shell.youngs_modulus, m.shell.poisson_ratio, m.shell.density) == (3.0e6, 0.4, 1010.0)
    assert m.squeeze_threshold == 0.12 and "explicit" in m.threshold_source
    assert "overridden" in m.shell.source and m.notes
    # model + yield: an elastic shell made plastic
    m = material_oracle(OBJECTS["rubber_duck"][0], "rubber_duck", {"model": "stvk_hencky_von_mises",
                                                                   "yield_stress": 2e5})
    assert m.shell.model == "stvk_hencky_von_mises" and m.shell.yield_stress == 2e5
    # a plastic model without a yield stress fails after merging, naming the field
    with pytest.raises(MaterialOracleError, match="yield_stress is required"):
        material_oracle(OBJECTS["rubber_duck"][0], "rubber_duck", {"model": "foam"})
    # OmegaConf structured config works as overrides too
    from omegaconf import OmegaConf
    oc = OmegaConf.structured(MaterialOverrides(density=1500.0))
    assert material_oracle(OBJECTS["clay"][0], "clay", oc).shell.density == 1500.0
    with pytest.raises(MaterialOracleError, match="unknown material override"):
        material_oracle(OBJECTS["clay"][0], "clay", {"youngs": 1e6})
    with pytest.raises(MaterialOracleError, match="squeeze_threshold 1.5 must be in"):
        material_oracle(OBJECTS["clay"][0], "clay", {"squeeze_threshold": 1.5})


def test_oracle_for_object_config():
    from conf.schema import ObjectConfig
    obj = ObjectConfig(name="can", display_name="Can", description=OBJECTS["can"][0], interior="cola",
                       material=MaterialOverrides(yield_stress=250e6))
    m = oracle_for_object(obj)
    assert m.matched_entry == "aluminium_can" and m.shell.yield_stress == 250e6


@pytest.mark.parametrize("bad,fragment", [
    ({"poisson_ratio": 0.5},
     "poisson_ratio 0.5 >= 0.5 makes the material incompressible (infinite lambda): use <= 0.49"),
    ({"poisson_ratio": 0.7}, "poisson_ratio 0.7 >= 0.5"),
    ({"poisson_ratio": -0.1}, "poisson_ratio -0.1 < 0"),
    ({"youngs_modulus": -5.0}, "youngs_modulus -5 must be > 0 Pa"),
    ({"youngs_modulus": 0.0}, "youngs_modulus 0 must be > 0 Pa"),
    ({"density": 2.7}, "not g/cm^3"),
    ({"density": -1.0}, "density -1 must be > 0"),
    ({"yield_stress": -3.0}, "yield_stress -3 must be > 0"),
])
def test_invalid_values_rejected_with_one_line_message(bad, fragment):
    base = {"model": "neo_hookean", "youngs_modulus": 1e6, "poisson_ratio": 0.45, "density": 1100.0,
            "source": "test"}
    with pytest.raises(MaterialOracleError) as info:
        validate_material({**base, **bad})
    assert fragment in str(info.value) and "\n" not in str(info.value)
    # the same message comes out of the oracle when an override carries the bad value
    if set(bad) <= {"poisson_ratio", "youngs_modulus", "density", "yield_stress"}:
        with pytest.raises(MaterialOracleError) as info:
            material_oracle(OBJECTS["rubber_ball"][0], "rubber_ball", bad)
        assert fragment in str(info.value) and "\n" not in str(info.value)


def test_model_and_effect_constraints():
    with pytest.raises(MaterialOracleError, match="model 'metal' is not a known model"):
        validate_material({"model": "metal", "youngs_modulus": 1e9, "poisson_ratio": 0.3, "density": 2000.0,
                           "source": "x"})
    with pytest.raises(MaterialOracleError, match="viscosity is required"):
        validate_material({"model": "fluid", "youngs_modulus": 1e8, "poisson_ratio": 0.49, "density": 1000.0,
                           "source": "x"})
    with pytest.raises(MaterialOracleError, match="yield_stress 2e\\+06 >= youngs_modulus"):
        validate_material({"model": "foam", "youngs_modulus": 1e6, "poisson_ratio": 0.3, "density": 30.0,
                           "yield_stress": 2e6, "source": "x"})
    shell = TABLE[0].shell
    with pytest.raises(Exception, match="needs a squeeze_threshold"):
        ObjectMaterials(shell=shell, effect="juice", squeeze_threshold=None)
    with pytest.raises(Exception, match="effect 'explode' is not a known effect"):
        ObjectMaterials(shell=shell, effect="explode")


# ----------------------------------------------------------------------------------------------- YAML objects
def _yaml_objects():
    files = sorted((ROOT / "conf" / "object").glob("*.yaml"))
    return [pytest.param(f, id=f.stem) for f in files]


@pytest.mark.parametrize("path", _yaml_objects() or [pytest.param(None, marks=pytest.mark.skip("no YAMLs yet"))])
def test_object_yaml_matches_intended_entry(path):
    from omegaconf import OmegaConf

    from conf.schema import ObjectConfig
    raw = OmegaConf.load(path)
    obj = OmegaConf.merge(OmegaConf.structured(ObjectConfig), raw)
    name = obj.name if obj.name in OBJECTS else path.stem
    if name not in OBJECTS:
        pytest.skip(f"{obj.name} is not one of the eight evaluation objects")
    m = oracle_for_object(obj)
    assert m.matched_entry == OBJECTS[name][2]
    assert m.effect == EXPECTED_EFFECT[m.matched_entry] or obj.interior is None


# ----------------------------------------------------------------------------------------------- LLM backend
VALID_ANSWER = {
    "shell": {"name": "tomato skin", "model": "fixed_corotated", "youngs_modulus": 2.0e6, "poisson_ratio": 0.45,
              "density": 1000.0, "yield_stress": None, "viscosity": None, "hardening": None,
              "source": "test server", "note": ""},
    "interior": {"name": "tomato juice", "model": "fluid", "youngs_modulus": 1.32e8, "poisson_ratio": 0.49,
                 "density": 1020.0, "viscosity": 0.005, "source": "test server"},
    "squeeze_threshold": 0.15, "threshold_source": "test server", "effect": "juice",
}


def _oracle_answer(mode: str, n: int, auth: str) -> tuple[int, str | None]:
    """The test endpoint's behaviour per mode."""
    if mode in ("good", "good2"):
        return 200, json.dumps(VALID_ANSWER)
    if mode == "fenced":
        return 200, "```json\n" + json.dumps(VALID_ANSWER) + "\n```"
    if mode == "badjson":
        return 200, "Sure! Here are the properties: {shell: rubber, key " + auth
    if mode == "schema":
        bad = json.loads(json.dumps(VALID_ANSWER))
        bad["shell"]["poisson_ratio"] = 0.5
        bad["colour"] = "red"
        return 200, json.dumps(bad)
    if mode == "slow":
        time.sleep(1.5)
        return 200, json.dumps(VALID_ANSWER)
    if mode == "unauthorized":
        return 401, None
    return 200, None


@pytest.fixture(scope="module")
def server():
    s = ChatEndpoint(_oracle_answer, lambda auth: {"error": f"invalid key {auth}"})
    yield s
    s.close()



def _cfg(server, mode, tmp_path, **kw):
    return OracleConfig(backend="llm", llm_url=server.url(mode), llm_model="test-model", api_key_env=KEY_ENV,
                        timeout_s=kw.pop("timeout_s", 5.0), cache_dir=str(tmp_path / "cache"), **kw)



def test_llm_valid_answer_and_cache(server, tmp_path, key_env):
    cfg = _cfg(server, "good", tmp_path)
    desc = OBJECTS["tomato"][0]
    m1 = material_oracle(desc, "tomato", None, "juice", cfg)
    assert m1.backend == "llm" and m1.matched_entry == "llm:test-model"
    assert m1.shell.youngs_modulus == 2.0e6 and m1.interior.model == "fluid" and m1.effect == "juice"
    assert server.hits["good"] == 1
    req = server.requests[-1]
    assert req["path"] == "/good/v1/chat/completions" and req["auth"] == f"Bearer {SECRET}"
    assert req["json"]["model"] == "test-model" and req["json"]["response_format"] == {"type": "json_object"}
    assert desc in req["json"]["messages"][-1]["content"]
    # second identical call: served from the disk cache, the server is not hit again
    m2 = material_oracle(desc, "tomato", None, "juice", cfg)
    assert m2 == m1 and server.hits["good"] == 1
    # the cache is JSON, keyed by the request, and holds no API key
    files = list((tmp_path / "cache").glob("*.json"))
    assert len(files) == 1
    record = json.loads(files[0].read_text())
    assert record["key"]["description"] == desc and record["key"]["model"] == "test-model"
    assert SECRET not in files[0].read_text()
    assert SECRET not in json.dumps(materials_to_dict(m1))
    # a different description, model or url is a new request
    material_oracle(desc + " (cherry)", "tomato", None, "juice", cfg)
    assert server.hits["good"] == 2
    material_oracle(desc, "tomato", None, "juice", _cfg(server, "good2", tmp_path))
    assert server.hits["good2"] == 1
    # overrides still win over the LLM, and interior None drops the LLM's interior
    m3 = material_oracle(desc, "tomato", {"youngs_modulus": 4e6, "squeeze_threshold": 0.2}, None, cfg)
    assert m3.shell.youngs_modulus == 4e6 and m3.squeeze_threshold == 0.2 and m3.interior is None
    assert any("dropped" in n for n in m3.notes)
    # a corrupted cache file is ignored and rewritten
    hits = server.hits["good"]
    path = (tmp_path / "cache" / files[0].name)
    path.write_text("{not json")
    assert material_oracle(desc, "tomato", None, "juice", cfg) == m1
    assert server.hits["good"] == hits + 1
    LLMAnswer.model_validate(json.loads(path.read_text())["answer"])


def test_llm_no_cache_dir_asks_every_time(server, tmp_path, key_env):
    cfg = _cfg(server, "fenced", tmp_path)
    cfg.cache_dir = None
    material_oracle("a fenced tomato", "tomato", None, "juice", cfg)
    material_oracle("a fenced tomato", "tomato", None, "juice", cfg)
    assert server.hits["fenced"] == 2  # (a ```json fence around the answer is accepted)


def test_llm_invalid_json(server, tmp_path, key_env):
    cfg = _cfg(server, "badjson", tmp_path)
    for _ in range(2):
        with pytest.raises(MaterialOracleError) as info:
            material_oracle("a tomato", "tomato", None, "juice", cfg)
        msg = str(info.value)
        assert server.url("badjson") + "/chat/completions" in msg and "invalid JSON" in msg
        assert "***" in msg  # the echoed key was redacted
        assert_no_secret(info.value)
    assert server.hits["badjson"] == 2  # failures are not cached
    assert not list((tmp_path / "cache").glob("*.json"))


def test_llm_schema_violation(server, tmp_path, key_env):
    with pytest.raises(MaterialOracleError) as info:
        material_oracle("a tomato", "tomato", None, "juice", _cfg(server, "schema", tmp_path))
    msg = str(info.value)
    assert server.url("schema") in msg and "violates the material schema" in msg
    assert "shell.poisson_ratio 0.5 >= 0.5" in msg and "colour" in msg and "\n" not in msg
    assert_no_secret(info.value)


def test_llm_timeout(server, tmp_path, key_env):
    t0 = time.monotonic()
    with pytest.raises(MaterialOracleError) as info:
        material_oracle("a slow tomato", "tomato", None, "juice", _cfg(server, "slow", tmp_path, timeout_s=0.3))
    assert time.monotonic() - t0 < 1.4
    assert str(info.value) == (f"LLM endpoint {server.url('slow')}/chat/completions timed out after 0.3 s: "
                               "raise oracle.timeout_s or use backend=table")
    assert_no_secret(info.value)


def test_llm_http_error_redacts_key(server, tmp_path, key_env):
    with pytest.raises(MaterialOracleError) as info:
        material_oracle("a tomato", "tomato", None, "juice", _cfg(server, "unauthorized", tmp_path))
    msg = str(info.value)
    assert "HTTP 401" in msg and KEY_ENV in msg and "***" in msg
    assert_no_secret(info.value)


def test_llm_config_errors(tmp_path, key_env):
    with pytest.raises(MaterialOracleError, match="llm_url is not set"):
        material_oracle("a tomato", "tomato", None, None, OracleConfig(backend="llm"))
    with pytest.raises(MaterialOracleError, match="backend 'gpt' must be"):
        material_oracle("a tomato", "tomato", None, None, OracleConfig(backend="gpt"))
    # a closed port on 127.0.0.1: unreachable, clear message, no key
    import socket
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    cfg = OracleConfig(backend="llm", llm_url=f"http://127.0.0.1:{port}/v1", api_key_env=KEY_ENV, timeout_s=2)
    with pytest.raises(MaterialOracleError, match="unreachable") as info:
        material_oracle("a tomato", "tomato", None, None, cfg)
    assert_no_secret(info.value)


def test_api_key_is_in_no_artifact_cache_file_or_log(server, tmp_path, key_env, caplog, capfd):
    """The key lives in the environment only.  After the real oracle step wrote its artifact and the LLM answer
    cache under the artifacts folder, was served again from disk, and failed on endpoints that echo the key back
    (HTTP 401 body, invalid JSON), the key is in no file under that folder and in no log line or output."""
    import logging

    from tasks.core.artifacts import read_artifact
    from tasks.physics.material_oracle import material_oracle_step

    caplog.set_level(logging.DEBUG)  # every logger, httpx and httpcore included
    root = tmp_path / "artifacts"
    oracle = {"backend": "llm", "llm_url": server.url("good"), "llm_model": "test-model", "api_key_env": KEY_ENV,
              "timeout_s": 5.0, "cache_dir": str(root / "llm-cache")}
    params = {"object.description": OBJECTS["tomato"][0], "object.name": "tomato", "object.interior": "juice",
              "oracle": oracle,
              "object.material": {k: None for k in ("model", "youngs_modulus", "poisson_ratio", "density",
                                                    "yield_stress", "squeeze_threshold")}}
    ref = material_oracle_step.run_local(root=str(root), scope="tomato", params=params)
    assert read_artifact(ref).attrs["materials"]["backend"] == "llm"
    assert material_oracle_step.run_local(root=str(root), scope="tomato", params=params).reused
    for mode in ("unauthorized", "badjson"):
        with pytest.raises(MaterialOracleError) as info:
            material_oracle_step.run_local(root=str(root), scope="tomato",
                                           params={**params, "oracle": {**oracle, "llm_url": server.url(mode)}})
        # as Prefect reports a failed task: message and traceback into the log
        logging.getLogger("virsqueezer").error("task failed", exc_info=info.value)
    # the key was really sent, and really echoed back by the failing endpoints
    assert {r["auth"] for r in server.requests[-3:]} == {f"Bearer {SECRET}"}
    files = [p for p in root.rglob("*") if p.is_file()]
    assert any(p.suffix == ".json" for p in files) and any(p.name == "zarr.json" for p in files)
    assert [p for p in files if SECRET.encode() in p.read_bytes()] == []
    out, err = capfd.readouterr()
    assert "task failed" in caplog.text and "***" in caplog.text
    assert SECRET not in caplog.text + out + err


# ------------------------------------------------------------------------------------------ the table file
def test_table_file_errors_name_the_entry_and_field(tmp_path):
    from tasks.physics.oracle.table import TABLE_PATH, MaterialTableError, load_table

    text = TABLE_PATH.read_text(encoding="utf-8")
    entries, interiors = load_table(TABLE_PATH)
    assert [e.key for e in entries] == [e.key for e in TABLE] and list(interiors) == list(INTERIORS)
    cases = {"      density: 1000.0\n": ("      density: 0.5\n", "entries.tomato.shell.density 0.5"),
             "interior: tomato_juice": ("interior: tomato_jus", "entries.tomato.interior 'tomato_jus'"),
             "effect: juice": ("effect: jus", "entries.tomato.effect 'jus'"),
             "    bulk_modulus: 2.2e+9": ("    bulk_modulus: -2.2e+9", "interiors.cola.material.youngs_modulus")}
    for old, (new, expected) in cases.items():
        assert old in text
        bad = tmp_path / "materials.yaml"
        bad.write_text(text.replace(old, new, 1), encoding="utf-8")
        with pytest.raises(MaterialTableError) as info:
            load_table(bad)
        assert expected in str(info.value) and "\n" not in str(info.value)


def test_table_fluids_store_their_bulk_modulus():
    """A fluid's E, nu in the table encode the liquid's bulk modulus K = E / (3 (1 - 2 nu)) given in the file."""
    assert INTERIORS["water"].material.bulk_modulus == pytest.approx(2.2e9, rel=1e-12)


def test_loose_stuffing_is_the_packed_stuffing_relaxed_by_van_wyks_cube_law():
    """The torn-out fibrefill is the packed stuffing (the core) relaxed to 1 / simulation.stuffing_packing of its
    volume: a cohesive foam of the same density (mass conserved) whose modulus and yield stress scale with the cube
    of the fibre volume fraction (van Wyk 1946): x packing^3 = 0.125 at the default 0.5."""
    from conf.schema import SimulationConfig

    loose, packed = INTERIORS["polyester_fibrefill"].material, INTERIORS["polyester_fibrefill"].core
    cube = SimulationConfig().stuffing_packing ** 3
    assert loose.model == "foam" and loose.density == packed.density
    assert loose.youngs_modulus == pytest.approx(packed.youngs_modulus * cube, rel=1e-12)
    assert loose.yield_stress == pytest.approx(packed.yield_stress * cube, rel=1e-12)
