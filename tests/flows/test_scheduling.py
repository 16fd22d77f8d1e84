"""The Dask priorities the evaluation grid submits its steps with: every object's set-up first, then largest first."""
from __future__ import annotations

import dask


def test_every_objects_set_up_outranks_every_rollout_and_larger_objects_go_first(compose_cfg):
    from flows.pipeline import PER_OBJECT, object_priorities, selected_objects, selected_variants, submit_object
    from flows.preflight import particle_bound

    cfg = compose_cfg("evaluate", [])
    objects = selected_objects(cfg)
    assert len(objects) == 8
    seen: dict[tuple[str, str, str], int] = {}

    def record(step, *, params, inputs, label, root, scope):
        seen[(scope, step.name, label)] = dask.get_annotations()["priority"]
        return step.name

    ranked = object_priorities(cfg, objects)
    for obj, priorities in ranked:
        submit_object(cfg, obj, selected_variants(cfg), call=record, priorities=priorities)
    set_up_names = {s.name for s in PER_OBJECT}
    set_up = {k: p for k, p in seen.items() if k[1] in set_up_names}
    rest = {k: p for k, p in seen.items() if k[1] not in set_up_names}
    assert len(set_up) == 8 * len(PER_OBJECT) and "mpm_rollout" in {k[1] for k in rest}
    assert min(set_up.values()) > max(rest.values())
    bounds = [particle_bound(cfg, obj) for obj, _ in ranked]
    assert bounds == sorted(bounds, reverse=True)
    by_object = {obj.name: {p for k, p in rest.items() if k[0] == obj.name} for obj, _ in ranked}
    assert all(len(p) == 1 for p in by_object.values())  # one priority per object for all its variants' steps
    order = [by_object[obj.name].pop() for obj, _ in ranked]
    assert order == [p.steps for _, p in ranked] and order == sorted(order, reverse=True) and len(set(order)) == 8
    assert ranked[0][0].name == "plush_toy"  # the largest simulation starts first
    # an object's report media: after its own steps, before the next object's, above nothing of the set-up
    media = [p.media for _, p in ranked]
    assert all(order[i] > media[i] > (order[i + 1] if i + 1 < 8 else 0) for i in range(8))


def test_without_priorities_submit_object_leaves_the_annotations_alone(compose_cfg):
    from flows.pipeline import selected_objects, selected_variants, submit_object

    cfg = compose_cfg("evaluate", ["object=clay"])
    seen = []

    def record(step, **_):
        seen.append(dask.get_annotations().get("priority"))
        return step.name

    with dask.annotate(priority=7):
        submit_object(cfg, selected_objects(cfg)[0], selected_variants(cfg), call=record)
    assert seen and set(seen) == {7}


def _run_order(config: dict) -> list[str]:
    """Order in which a real one-thread Dask worker runs: a blocker, then six steps with an input at priority 1
    and six steps without inputs (one task group, like the grid's ``object_model`` steps) at priority 10."""
    import time

    from distributed import Client, LocalCluster

    def step(name, *_):
        time.sleep(0.05)
        return name, time.monotonic()

    with dask.config.set(config), \
            LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster, \
            Client(cluster) as client:
        source = client.submit(step, "source", key="source-0")
        source.result()
        with dask.annotate(priority=5):
            futures = [client.submit(time.sleep, 0.5, key="blocker-0")]
        with dask.annotate(priority=1):
            futures += [client.submit(step, f"rollout{i}", source, key=f"rollout-{i}") for i in range(6)]
        with dask.annotate(priority=10):
            futures += [client.submit(step, f"set_up{i}", key=f"set_up-{i}") for i in range(6)]
        done = [f.result() for f in futures[1:]]
    return [name for name, _ in sorted(done, key=lambda r: r[1])]


def test_the_local_schedulers_config_runs_inputless_set_up_steps_by_priority_where_dasks_default_starves_them():
    """Dask's default queues steps without inputs until a worker is nearly empty, while steps with inputs are handed
    out eagerly: lower-priority rollouts then run between the set-up steps; our scheduler config runs the set-up
    first."""
    from flows.runtime import LOCAL_SCHEDULER_CONFIG

    ours = _run_order(LOCAL_SCHEDULER_CONFIG)
    assert [n[:6] for n in ours] == ["set_up"] * 6 + ["rollou"] * 6
    default = _run_order({})
    assert [n[:6] for n in default].index("rollou") < 6  # the starvation this config is for
