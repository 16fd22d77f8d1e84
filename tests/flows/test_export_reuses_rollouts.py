"""``flows.export`` / ``flows.squeeze`` reuse the grid's rollouts: their configs differ from ``flows.evaluate``'s only
in ``mpm.threads`` (2 for one scene, 1 per Dask worker), which splits the same particle kernel and is left out of the
rollout's cache key, so the same scene hits the same cache entry; a value that changes the physics still re-keys."""
from __future__ import annotations

from tasks.core.artifacts import ArtifactRef


def _keys(overrides_eval=(), overrides_squeeze=()):
    from flows.pipeline import STEPS, step_params
    from tasks.core.step import step_key
    from tests.conftest import compose

    e = compose("evaluate", list(overrides_eval))
    s = compose("squeeze", ["object=tomato", *overrides_squeeze])
    inputs = {}
    keys = {}
    for step in STEPS:
        refs = {n: inputs[n] for n in step.spec.inputs}
        pe = step_params(step, e, e.catalog.tomato, e.variants.full)
        ps = step_params(step, s, s.object, s.variant)
        keys[step.name] = (step_key(step.name, step.version, "tomato", pe, refs, step.spec.unkeyed),
                           step_key(step.name, step.version, "tomato", ps, refs, step.spec.unkeyed), pe, ps)
        inputs[step.name] = ArtifactRef(rel=f"tomato/{step.name}/x.zarr", digest=keys[step.name][0], step=step.name,
                                        scope="tomato")
    return keys


def test_squeeze_and_export_hit_the_grid_s_rollout_entry_and_still_run_on_two_threads():
    keys = _keys()
    rollout_eval, rollout_squeeze, params_eval, params_squeeze = keys["mpm_rollout"]
    assert params_eval["mpm"]["threads"] == 1 and params_squeeze["mpm"]["threads"] == 2  # each flow runs as set
    assert rollout_eval == rollout_squeeze
    assert all(k[0] == k[1] for k in keys.values())  # every step of the scene, not only the rollout


def test_a_value_that_changes_the_physics_is_still_in_the_key():
    keys = _keys(overrides_squeeze=["mpm.max_speed_cfl=0.3"])
    assert keys["mpm_rollout"][0] != keys["mpm_rollout"][1]
