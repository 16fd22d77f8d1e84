"""Hydra configuration: structured schemas catch typos, ranges are validated, the catalog is complete."""
import subprocess
import sys
from pathlib import Path

import pytest
from hydra.errors import ConfigCompositionException
from omegaconf.errors import ConfigKeyError, ValidationError

from conf.schema import ConfigError, validate

REPO = Path(__file__).resolve().parents[2]
EIGHT = ["can", "plush_toy", "rubber_duck", "clay", "tomato", "orange", "rubber_ball", "paper_cup"]


def test_evaluate_has_the_eight_objects_and_validates(compose_cfg):
    cfg = compose_cfg("evaluate", [])
    assert list(cfg.grid.objects) == EIGHT
    assert sorted(cfg.catalog) == sorted(EIGHT)
    assert cfg.object is None
    validate(cfg)
    for name in EIGHT:
        obj = cfg.catalog[name]
        assert obj.name == name and obj.description and obj.geometry.kind


def test_object_override_restricts_the_grid(compose_cfg):
    from flows.pipeline import selected_objects

    cfg = compose_cfg("evaluate", ["object=orange"])
    assert [o.name for o in selected_objects(cfg)] == ["orange"]
    assert [o.name for o in selected_objects(compose_cfg("evaluate", ["grid.objects=[can,clay]"]))] == ["can", "clay"]


@pytest.mark.parametrize("override", ["control.force.gama=2.0", "signal.rate=3", "sampling.surface_point=5"])
def test_typo_in_override_is_an_error(compose_cfg, override):
    with pytest.raises((ConfigCompositionException, ConfigKeyError)) as exc:
        compose_cfg("squeeze", [override])
    assert override.split("=")[0].split(".")[-1] in str(exc.value) + str(exc.value.__cause__)


def test_wrong_type_is_an_error(compose_cfg):
    with pytest.raises((ConfigCompositionException, ValidationError)):
        compose_cfg("squeeze", ["control.force.gamma=steep"])


def test_unknown_object_is_an_error(compose_cfg):
    with pytest.raises(ConfigCompositionException, match="banana"):
        compose_cfg("squeeze", ["object=banana"])


@pytest.mark.parametrize("override,key", [
    ("control.force.gamma=-1", "control.force.gamma"),
    ("control.force.beta=1.5", "control.force.beta"),
    ("control.force.weights=[1,1]", "control.force.weights"),
    ("signal.duration=0", "signal.duration"),
    ("control.smoothing.ema_alpha=0", "control.smoothing.ema_alpha"),
    # a zero grid, before anything runs (the MPM step is the last and the costliest)
    ("sampling.particle_spacing=0", "sampling.particle_spacing"),
    ("mpm.dx=0", "mpm.dx"),
    ("mpm.cells_across=0", "mpm.cells_across"),
    ("mpm.particles_per_cell=0", "mpm.particles_per_cell"),
    ("simulation.force_balance=palm", "simulation.force_balance"),
    ("simulation.force_balance_friction=0", "simulation.force_balance_friction"),
    ("simulation.release_margin_cells=-1", "simulation.release_margin_cells"),
    ("simulation.stuffing_cohesion=-0.5", "simulation.stuffing_cohesion"),
    ("simulation.gravity_preload_frames=-1", "simulation.gravity_preload_frames"),
    ("simulation.gravity_preload_passes=0", "simulation.gravity_preload_passes"),
    ("simulation.gravity_preload_tolerance=0", "simulation.gravity_preload_tolerance"),
    # the object's own material values (they win over the oracle) and geometry
    ("object.material.youngs_modulus=-2e6", "object.material.youngs_modulus"),
    ("object.material.poisson_ratio=0.5", "object.material.poisson_ratio"),
    ("object.material.poisson_ratio=-0.1", "object.material.poisson_ratio"),
    ("object.material.density=0", "object.material.density"),
    ("object.material.squeeze_threshold=1.5", "object.material.squeeze_threshold"),
    ("object.geometry.size=[0.05,0,0.05]", "object.geometry.size"),
    ("object.geometry.kind=mesh", "object.geometry.path"),
    # the material oracle
    ("oracle.backend=gpt", "oracle.backend"),
    ("oracle.timeout_s=0", "oracle.timeout_s"),
    ("oracle.backend=llm", "oracle.llm_url"),
])
def test_out_of_range_values_name_the_key(compose_cfg, override, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")) as exc:
        validate(compose_cfg("squeeze", [override]))
    assert str(exc.value).startswith(key) and "\n" not in str(exc.value)


@pytest.mark.parametrize("override,key", [
    ("catalog.rubber_ball.material.poisson_ratio=0.5", "catalog.rubber_ball.material.poisson_ratio"),
    ("catalog.clay.material.youngs_modulus=-1", "catalog.clay.material.youngs_modulus"),
    ("grid.objects=[rubber_ball,banana]", "grid.objects"),
])
def test_grid_objects_are_checked_with_the_key_to_override(compose_cfg, override, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        validate(compose_cfg("evaluate", ["grid.objects=[rubber_ball,clay]", override]))
    # an object outside the grid is not run, so its values are not checked
    validate(compose_cfg("evaluate", ["catalog.can.material.poisson_ratio=0.5", "grid.objects=[clay]"]))


def test_huge_recording_is_refused_before_it_is_read_or_hashed(compose_cfg, tmp_path):
    from tasks.control.recording import MAX_RECORDING_BYTES

    huge = tmp_path / "huge.csv"
    with open(huge, "wb") as fh:  # sparse: st_size above the limit, no disk used
        fh.write(b"time,flex_thumb\n")
        fh.truncate(MAX_RECORDING_BYTES + 1)
    from flows.preflight import preflight

    with pytest.raises(SystemExit) as exc:
        preflight(compose_cfg("squeeze", ["signal=csv", f"signal.path={huge}"]))
    msg = str(exc.value)
    assert msg.startswith("input error: signal.path") and str(huge) in msg and "256.0 MiB limit" in msg
    assert "cut it" in msg and "\n" not in msg


def test_step_params_hold_exactly_what_each_step_reads(compose_cfg):
    from flows.pipeline import STEPS, step_params

    base = compose_cfg("squeeze", ["object=tomato"])
    other = compose_cfg("squeeze", ["object=tomato", "control.force.gamma=2.5"])
    a = {s.name: step_params(s, base, base.object, base.variant) for s in STEPS}
    b = {s.name: step_params(s, other, other.object, other.variant) for s in STEPS}
    assert [k for k in a if a[k] != b[k]] == ["force_coefficients"]
    assert a["force_coefficients"]["control.force"]["gamma"] == 1.5


def test_cfg_job_prints_the_config():
    out = subprocess.run([sys.executable, "-m", "flows.evaluate", "--cfg", "job"], cwd=REPO,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "catalog:" in out.stdout and "gamma: 1.5" in out.stdout and "rubber_duck" in out.stdout


@pytest.mark.parametrize("override,key,value", [
    ("signal.duration=inf", "signal.duration", "inf"),
    ("control.smoothing.frame_rate=inf", "control.smoothing.frame_rate", "inf"),
    ("control.displacement.eta=inf", "control.displacement.eta", "inf"),
    ("control.contact.sigma_max=inf", "control.contact.sigma_max", "inf"),
    ("signal.sensor_rate=nan", "signal.sensor_rate", "nan"),
    ("object.material.youngs_modulus=inf", "object.material.youngs_modulus", "inf"),
    ("control.force.weights=[1,1,1,1,-inf]", "control.force.weights[4]", "-inf"),
    ("mpm.courant=nan", "mpm.courant", "nan"),
])
def test_non_finite_numbers_are_refused_everywhere(compose_cfg, override, key, value):
    """inf passes every '> 0' check and nan every comparison: any non-finite number in the config is refused,
    whichever group it is in."""
    with pytest.raises(ConfigError) as exc:
        validate(compose_cfg("squeeze", [override]))
    assert str(exc.value) == f"{key} must be a finite number, got {value}"


@pytest.mark.parametrize("override,line", [
    ("+control.force.gama=2", "control.force.gama is not a key of ForceConfig (it would be ignored): did you mean "
                              "control.force.gamma?"),
    ("+catalog.clay.material.youngs_modulu=2e6", "catalog.clay.material.youngs_modulu is not a key of "
                                                 "MaterialOverrides (it would be ignored): did you mean "
                                                 "catalog.clay.material.youngs_modulus?"),
    ("+limits.max_frame=10", "limits.max_frame is not a key of LimitsConfig (it would be ignored): did you mean "
                             "limits.max_frames?"),
])
def test_a_key_added_with_plus_to_a_structured_group_is_refused(compose_cfg, override, line):
    """Hydra's hint for a typo ('use +key=value to append') makes the typo a new key that nothing reads."""
    with pytest.raises(ConfigError) as exc:
        validate(compose_cfg("evaluate", [override]))
    assert str(exc.value) == line


@pytest.mark.parametrize("override,line", [
    ("grid.seeds=[]", "grid.seeds is empty: give at least one seed, e.g. grid.seeds=[0,1,2], or leave it unset"),
    ("grid.seeds=[0,1,0]", "grid.seeds lists a seed twice: [0, 1, 0]"),
    ("grid.seeds=[-1,2]", "grid.seeds must be >= 0, got [-1, 2]"),
    ("sampling.seed=-3", "sampling.seed must be >= 0, got -3"),
    ("runner.kind=dusk", "runner.kind must be one of sequential, threads, dask, got 'dusk'"),
])
def test_bad_seed_grid_or_runner_is_one_line_naming_the_key(compose_cfg, override, line):
    with pytest.raises(ConfigError) as exc:
        validate(compose_cfg("evaluate", [override]))
    assert str(exc.value) == line


def test_an_empty_grid_is_an_error(compose_cfg):
    with pytest.raises(ConfigError) as exc:
        validate(compose_cfg("evaluate", ["grid.objects=[]"]))
    assert str(exc.value) == ("grid.objects is empty: name at least one object, e.g. [rubber_ball] (known ['can', "
                              "'clay', 'orange', 'paper_cup', 'plush_toy', 'rubber_ball', 'rubber_duck', 'tomato'])")
    with pytest.raises(ConfigError) as exc:
        validate(compose_cfg("evaluate", ["grid.variants=[]"]))
    assert str(exc.value) == "grid.variants is empty: name at least one variant, e.g. [full]"
    validate(compose_cfg("evaluate", ["grid.objects=[]", "object=clay"]))  # one object selected: no grid needed


def test_seed_grid_runs_each_seed_in_its_own_scope(compose_cfg, tmp_path):
    """grid.seeds: one run per seed, sampling.seed set per run; seed 0 keeps the object's own scope, seed k is
    ``<object>@seed<k>``; unset, the grid is the one sampling.seed."""
    from flows.pipeline import run_object_local, selected_seeds, with_seed

    cfg = compose_cfg("evaluate", ["object=rubber_ball", "grid.seeds=[0,2]", "sampling.surface_points=300",
                                   "sampling.particle_spacing=0.008"])
    assert selected_seeds(cfg) == [0, 2]
    assert selected_seeds(compose_cfg("evaluate", ["sampling.seed=5"])) == [5]
    refs = {seed: run_object_local(with_seed(cfg, seed), cfg.object, None, tmp_path, until="object_model")["object_model"]
            for seed in selected_seeds(cfg)}
    assert Path(refs[0].path).relative_to(tmp_path.resolve()).parts[:2] == ("rubber_ball", "object_model")
    assert Path(refs[2].path).relative_to(tmp_path.resolve()).parts[:2] == ("rubber_ball@seed2", "object_model")
    assert refs[0].digest != refs[2].digest
