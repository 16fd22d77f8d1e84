"""Where real rollouts spend their time:  ``python -m flows.bench.scenes`` (per Warp kernel and per phase).

    python -m flows.bench.scenes                               # plush toy, can, rubber ball; 20 frames each
    python -m flows.bench.scenes objects=[can] frames=null      # the whole rollout
    python -m flows.bench.scenes repeats=3 reference=false

Each scene is the evaluation grid's full variant (``conf/evaluate.yaml``, one thread per scene as ``flows.evaluate``
runs it) through the rollout step's own function, over its first ``frames`` output frames: once profiled
(:func:`tasks.verification.rollout_profile.profiled`: every Warp launch and the rollout's and the solver's Python
phases, split into the gravity preload and the squeeze), then ``repeats`` times plain for its seconds (the median;
the squeeze's throughput = particles x substeps / its seconds, the preload's substeps not counted).  With
``reference`` the MPM benchmark's one-thread run (``flows.bench.mpm``'s falling cube, 64^3 grid) is timed in the
same sitting for the ratio.  Each scene's squeeze is also set against its floor on one core
(:func:`tasks.verification.mpm_floor.scene_floor`: the compulsory bytes of its particle state and the fixed-corotated
flop count, a lower bound for scenes with plastic or membrane particles).  Config: ``conf/study/bench_scenes.yaml`` (keys:
:class:`conf.study.schema.ScenesBenchConfig`).  Writes ``<out>/scenes.json`` and ``scenes.md``.
"""
from __future__ import annotations

import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import hydra
import numpy as np
from omegaconf import DictConfig, OmegaConf

from conf.study.schema import register_study_configs

register_study_configs()


def reference_throughput() -> float:
    """M particle-substeps per thread CPU second of the MPM benchmark's one-thread Warp run (its default scene, 100
    substeps, best of 3), in a fresh process: CPU seconds, as the scenes' figures."""
    from tasks.verification.mpm_throughput import make_scene

    scene = make_scene(64, 0.4, 2, 1.0e5, 0.3, 1000.0, 1.0, 0.3)
    path = os.path.join(tempfile.mkdtemp(prefix="bench_scenes_"), "scene.npz")
    np.savez(path, **scene)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(Path(__file__).resolve().parents[2]),
                                                       os.environ.get("PYTHONPATH", "")]))
    out = subprocess.run([sys.executable, "-m", "tasks.verification.mpm_throughput", "--scene", path, "--threads",
                          "1", "--substeps", "100", "--repeats", "3"], capture_output=True, text=True, env=env,
                         timeout=1800, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])["throughput_cpu"] / 1e6


def rollout_inputs(obj: str, root: str, overrides: list[str]) -> tuple[dict, Any]:
    """The inputs of ``obj``'s full-variant rollout as the pipeline gives them (its per-object steps run or read
    from the cache under ``root``, :func:`flows.pipeline.run_object_local`) and the composed config."""
    from flows.pipeline import evaluate_config, run_object_local, step_params
    from tasks.core.artifacts import read_artifact
    from tasks.physics.mpm_rollout import mpm_rollout_step

    cfg = evaluate_config([f"object={obj}", "variant=full", f"paths.artifacts={root}", *overrides])
    refs = run_object_local(cfg, cfg.object, None, root, until="gravity_preload")
    params = step_params(mpm_rollout_step, cfg, cfg.object, cfg.variant)
    arts = {n: read_artifact(refs[n]) for n in mpm_rollout_step.spec.inputs}
    return {"arts": arts, "params": params}, cfg



@hydra.main(version_base="1.3", config_path="../../conf", config_name="study/bench_scenes")
def main(cfg: DictConfig) -> dict:
    from tasks.core.machine_rates import one_core_rates
    from tasks.core.tables import markdown_table
    from tasks.verification.mpm_floor import scene_floor
    from tasks.verification.rollout_profile import (
        kernel_rows,
        phase_rows,
        preload_timed,
        profiled,
        run_rollout,
        summary,
    )

    a = OmegaConf.to_container(cfg, resolve=True)
    if a["frames"] is not None and a["frames"] < 1:
        raise SystemExit(f"input error: frames must be >= 1 (output frames per rollout) or null, got {a['frames']}")
    if a["repeats"] < 0:
        raise SystemExit(f"input error: repeats must be >= 0, got {a['repeats']}")
    machine = f"{os.cpu_count()}-core {platform.processor() or platform.machine()}"
    try:
        machine = f"{os.cpu_count()}-core " + next(line.split(":", 1)[1].strip() for line in
                                                  open("/proc/cpuinfo") if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    lines = [f"# Rollout profile ({time.strftime('%Y-%m-%d %H:%M')}, {machine}, load {os.getloadavg()[0]:.1f})", "",
             f"Full variant, default config, first {a['frames'] or 'all'} output frames"
             + (f", overrides {' '.join(a['overrides'])}" if a["overrides"] else "") + "."]
    report: dict = {"machine": machine, "frames": a["frames"], "scenes": {}, "rates": one_core_rates()}
    for obj in a["objects"]:
        inputs, _ = rollout_inputs(obj, a["artifacts"], list(a["overrides"]))
        run_rollout(inputs, 1)  # warm-up: kernels compiled or loaded from Warp's cache
        with profiled() as prof:
            run_rollout(inputs, a["frames"])
        s = summary(prof)
        plain = []
        for _ in range(a["repeats"]):
            with preload_timed() as pre:
                start, cpu = time.perf_counter(), time.process_time()
                run_rollout(inputs, a["frames"])
                wall, cpu = time.perf_counter() - start, time.process_time() - cpu
            plain.append((wall, cpu, sum(w for w, _ in pre), sum(c for _, c in pre)))
        if plain:
            s["plain_seconds"] = statistics.median(w for w, _, _, _ in plain)
            s["plain_cpu_seconds"] = statistics.median(c for _, c, _, _ in plain)
            s["plain_squeeze_seconds"] = statistics.median(w - pw for w, _, pw, _ in plain)
            s["plain_squeeze_cpu_seconds"] = statistics.median(c - pc for _, c, _, pc in plain)
            s["plain_throughput"] = s["particles"] * s["substeps"] / s["plain_squeeze_cpu_seconds"] / 1e6
        s["floor"] = scene_floor(s, report["rates"])
        report["scenes"][obj] = {**s, "phases": phase_rows(prof), "kernels": kernel_rows(prof)}
        lines += ["", f"## {obj}", "",
                  f"{s['particles']:,} particles, grid {'x'.join(map(str, s['grid_dims']))} = {s['grid_nodes']:,} "
                  f"nodes; per substep the grid update runs over {s['box_nodes']:,.0f} nodes "
                  f"({100 * s['box_share']:.1f} % of the grid), {s['mass_nodes']:,.0f} of them with mass "
                  f"({100 * s['mass_share']:.1f} %). Squeeze: {s['substeps']:,} substeps, {s['squeeze_seconds']:.2f} "
                  f"CPU s profiled ({s['throughput']:.2f} M particle-substeps/s), gravity preload "
                  f"{s['preload_seconds']:.2f} CPU s"
                  + (f"; plain run (median of {len(plain)}): {s['plain_seconds']:.2f} s wall, "
                     f"{s['plain_cpu_seconds']:.2f} s CPU, squeeze {s['plain_squeeze_seconds']:.2f} s wall, "
                     f"{s['plain_squeeze_cpu_seconds']:.2f} s CPU = {s['plain_throughput']:.2f} M particle-substeps "
                     "per CPU second" if plain else "") + ". " + s["floor"]["text"] + ".", "",
                  markdown_table(["phase", "squeeze CPU s", "% of squeeze", "preload CPU s"],
                                 report["scenes"][obj]["phases"]), "",
                  markdown_table(["kernel / function", "kind", "calls", "squeeze CPU s", "us per call",
                                  "ns per launched thread"], report["scenes"][obj]["kernels"])]
        print("\n".join(lines[-6:]), flush=True)
    if a["reference"]:
        ref = reference_throughput()
        report["reference_throughput"] = ref
        lines += ["", f"MPM benchmark, one thread, same sitting: {ref:.2f} M particle-substeps per CPU second; the "
                  "scenes' squeeze "
                  "reaches " + ", ".join(
                      f"{obj} {100 * s.get('plain_throughput', s['throughput']) / ref:.0f} %"
                      for obj, s in report["scenes"].items()) + " of it."]
        print(lines[-1])
    out = Path(a["out"])
    out.mkdir(parents=True, exist_ok=True)
    (out / "scenes.json").write_text(json.dumps(report, indent=2))
    (out / "scenes.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {out / 'scenes.json'} and {out / 'scenes.md'}")
    return report


if __name__ == "__main__":
    main()
