"""Structured schemas of the research studies and benchmarks (``flows/studies/``, ``flows/bench/``).

Each study's own keys sit at the root of its config (``python -m flows.studies.ball travel=3 spacings=[2]``).  The
studies that run the pipeline's steps (``ball``, ``fingers``) extend the pipeline's :class:`conf.schema.Config`:
the MPM, sampling and object settings their runs use are the pipeline's own subtrees, overridden with Hydra's
syntax (``mpm.dx=0.008 sampling.thin_wall_layers=3``) and type-checked like a pipeline run's.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

from conf.schema import Config

FINGER_MODES = ("grid_dirichlet", "grid_particles", "surface_dirichlet", "surface_collider")


@dataclass
class BallStudyConfig(Config):
    """``python -m flows.studies.ball`` (the rubber ball between two flats against its FE reference).

    spacings: finer particle spacings (mm) run beside the default (the grid refines with them).  travel: each flat's
    travel (mm).  frames: output frames of the squeeze (1/30 s each).  plates: the flats, ``grid`` (grid-node slip
    points) and/or ``surface`` (plane colliders).  hold: then hold the flats still this long (s).  fe_step: the FE's
    depth increment (mm; a 1.5 mm wall needs 0.125).  out: folder of ``ball_study.md``.  The runs' artifacts:
    ``paths.artifacts``.
    """

    spacings: list[float] = field(default_factory=lambda: [3.0, 2.0])
    travel: float = 6.0
    frames: int = 60
    plates: list[str] = field(default_factory=lambda: ["grid"])
    hold: float = 0.0
    fe_step: float = 0.25
    out: str = "reports/ball"


@dataclass
class FingerStudyConfig(Config):
    """``python -m flows.studies.fingers`` (finger modes compared on Table 2).

    objects: the objects run.  modes: finger modes (``FINGER_MODES``).  spacings: finer particle spacings (mm) run
    beside the default, coarse to fine.  out: folder of ``finger_study.md``.  The runs' artifacts:
    ``paths.artifacts``.
    """

    objects: list[str] = field(default_factory=lambda: ["rubber_ball", "clay", "rubber_duck"])
    modes: list[str] = field(default_factory=lambda: list(FINGER_MODES))
    spacings: list[float] = field(default_factory=list)
    out: str = "reports/fingers"


@dataclass
class ForceMatchStudyConfig(Config):
    """``python -m flows.studies.force_match`` (reaction- vs indentation-matched constants of the force-driven
    ablation, docs/results/force-matched-ablation.md).

    objects: the objects run.  simulate: simulate the force-driven squeeze at the reaction-matched constant over the
    calibration window (one windowed rollout per object) instead of reading its indentation off the calibration
    runs.  out: folder of ``force_match_study.md`` and ``.csv``.  The runs' artifacts: ``paths.artifacts``.
    """

    objects: list[str] = field(default_factory=lambda: ["can", "plush_toy", "rubber_duck", "clay", "tomato", "orange",
                                                        "rubber_ball", "paper_cup"])
    simulate: bool = False
    out: str = "reports/force_match"


@dataclass
class ContactStudyConfig:
    """``python -m flows.studies.contact`` (grid vs surface contact against closed forms).

    hertz_cells: R / dx of the Hertz sphere.  hertz_nu: its Poisson ratios.  uniaxial_cells: L / dx of the cube.
    nu: Poisson ratios (uniaxial).  indent_cells: contact radius / dx of the rigid-sphere indentation.
    finger_cells: contact radius / dx (at 2 mm) of the collider finger.  modes: contact of the Hertz cases
    (``grid``, ``surface``).  uniaxial_modes: plates (``grid``, ``surface``, ``pins``).  out: folder of
    ``contact_study.md``.
    """

    hertz_cells: list[int] = field(default_factory=lambda: [8, 12, 16])
    hertz_nu: list[float] = field(default_factory=lambda: [0.45, 0.0])
    uniaxial_cells: list[int] = field(default_factory=lambda: [8, 12, 16])
    nu: list[float] = field(default_factory=lambda: [0.3, 0.45, 0.49])
    indent_cells: list[float] = field(default_factory=lambda: [1.5, 2.0, 2.7])
    finger_cells: list[float] = field(default_factory=lambda: [1.0, 1.5, 2.0])
    modes: list[str] = field(default_factory=lambda: ["grid", "surface"])
    uniaxial_modes: list[str] = field(default_factory=lambda: ["grid", "surface", "pins"])
    out: str = "reports/contact"


@dataclass
class MPMBenchConfig:
    """``python -m flows.bench.mpm`` (our Warp MLS-MPM against a Taichi peer on the same falling cube).

    n_grid: grid nodes per axis.  cube: cube side (m) in the unit box.  ppc_axis: particles per cell per axis.
    E (Pa), nu, rho (kg/m^3): the cube's material.  v0: initial downward speed (m/s).  courant: of the P-wave speed.
    substeps: per timed run.  repeats: timed runs per process.  rounds: interleaved rounds of fresh processes (the
    best is kept).  polar_iters: quaternion polar iterations per substep (ours and the taichi-quat peer).
    threads: CPU threads of our solver (None: all cores; 1-thread runs are added).  skip_taichi: Warp alone.
    quick: 32^3 grid, 40 substeps, 1 round.  out: folder of ``benchmark.json`` and ``benchmark.md``.
    """

    n_grid: int = 64
    cube: float = 0.4
    ppc_axis: int = 2
    E: float = 1.0e5
    nu: float = 0.3
    rho: float = 1000.0
    v0: float = 1.0
    courant: float = 0.3
    substeps: int = 100
    repeats: int = 3
    rounds: int = 2
    polar_iters: int = 1
    threads: Optional[int] = None
    skip_taichi: bool = False
    quick: bool = False
    out: str = "reports/benchmark"


@dataclass
class ScenesBenchConfig:
    """``python -m flows.bench.scenes`` (where real rollouts spend their time: per kernel and per phase).

    objects: the scenes (``conf/object``), each at the evaluation grid's full variant (``conf/evaluate.yaml``).
    frames: output frames of each rollout (None: all; the first ones include the gravity preload and the squeeze's
    onset, not a late rupture).  repeats: plain (unprofiled) runs per scene for its seconds, the median kept.
    overrides: pipeline keys for every scene (e.g. ``[mpm.threads=2]``).  artifacts: where the scenes' per-object
    inputs are cached.  reference: also time the MPM benchmark's one-thread run (``flows.bench.mpm``'s scene) for
    the ratio.  out: folder of ``scenes.json`` and ``scenes.md``.
    """

    objects: list[str] = field(default_factory=lambda: ["plush_toy", "can", "rubber_ball"])
    frames: Optional[int] = 20
    repeats: int = 1
    overrides: list[str] = field(default_factory=list)
    artifacts: str = "artifacts"
    reference: bool = True
    out: str = "reports/bench_scenes"


@dataclass
class RenderBenchConfig:
    """``python -m flows.bench.render`` (the Gaussian rasteriser's time per frame against its physical floor).

    resolutions: px (None: the G-buffer's ``render.width`` and the videos' ``render.video_width``).  sizes: Gaussian
    counts (None: the grid's ``sampling.surface_points`` alone and with the most released particles).  backends:
    ``torch``, ``warp-scalar``, ``warp``.
    """

    resolutions: Optional[list[int]] = None
    sizes: Optional[list[int]] = None
    backends: list[str] = field(default_factory=lambda: ["torch", "warp-scalar", "warp"])


@dataclass
class OverheadBenchConfig:
    """``python -m flows.bench.overhead`` (what one cached Prefect task costs outside the step's compute).

    chains: source steps.  fan: consumer steps per source.  mb: size of each source artifact (MB).  workers: Dask
    worker processes.  artifacts: artifacts folder (None: a new temporary folder).
    """

    chains: int = 8
    fan: int = 11
    mb: float = 3.0
    workers: int = 2
    artifacts: Optional[str] = None


@dataclass
class DiffusionGridRows:
    """The default evaluation grid's diffusion rows, as ``flows.bench.diffusion`` costs them (``conf/evaluate.yaml``,
    ``conf/render``, ``conf/generation``).

    clips: views generated (8 objects x 2 variants x 4 views; an upper bound: diffusers runs only where material is
    released).  frames: rendered frames per view (3 s at 30 Hz, ``render.frame_stride`` 2).  overlap:
    ``generation.overlap``.  steps: ``generation.steps``.  strength: ``generation.strength`` (the video pass runs
    int(steps x strength) steps).
    """

    clips: int = 64
    frames: int = 45
    overlap: int = 4
    steps: int = 20
    strength: float = 0.75


@dataclass
class GPUPeaks:
    """GPU figures of ``flows.bench.diffusion``: estimates (counted FLOPs / (peak x utilization)), never measured.

    utilization: the assumed share of peak a diffusers UNet step sustains (not measured here).  peaks: dense 16-bit
    tensor-core TFLOPS (fp32 accumulate) per GPU, from the vendors' datasheets.
    """

    utilization: float = 0.4
    peaks: dict[str, float] = field(default_factory=lambda: {
        "A100 (bf16, 312 TFLOPS)": 312.0, "RTX 4090 (fp16, 165 TFLOPS)": 165.0, "T4 (fp16, 65 TFLOPS)": 65.0})


@dataclass
class DiffusionBenchConfig:
    """``python -m flows.bench.diffusion`` (one denoising step of the video generator with random weights of the real
    sizes, and the default grid's diffusion rows derived from it).

    sizes: square frame sides (px).  dtypes: ``float32``, ``bfloat16``, ``float16``.  frames_timed: frames actually
    run per step (the window's cost is extrapolated from them by counted FLOPs).  window: frames of the motion
    module's window (the figure reported).  vae: also time one VAE encode and decode per size and dtype.  threads:
    torch threads (``VIRSQUEEZER_TORCH_THREADS`` overrides; the cores are shared, 1 is the stable figure).  grid: the
    rows costed.  gpus: the GPU estimates' basis.
    """

    sizes: list[int] = field(default_factory=lambda: [256, 512])
    dtypes: list[str] = field(default_factory=lambda: ["float32", "bfloat16"])
    frames_timed: list[int] = field(default_factory=lambda: [1, 2])
    window: int = 16
    vae: bool = True
    threads: int = 1
    grid: DiffusionGridRows = field(default_factory=DiffusionGridRows)
    gpus: GPUPeaks = field(default_factory=GPUPeaks)


def register_study_configs() -> None:
    """Register every study's schema with Hydra's ConfigStore (``<name>_schema`` in each ``conf/study/<name>.yaml``;
    the convergence, render-knob and stability schemas by their own modules), and the pipeline's."""
    from hydra.core.config_store import ConfigStore

    from conf.study.convergence_schema import register_convergence_config
    from conf.study.render_convergence_schema import register_render_study_config
    from conf.study.stability_schema import register_stability_config

    register_convergence_config()  # and the pipeline's (conf.schema.register_configs)
    register_render_study_config()
    register_stability_config()
    store = ConfigStore.instance()
    for name, node in (("ball_schema", BallStudyConfig), ("fingers_schema", FingerStudyConfig),
                       ("force_match_schema", ForceMatchStudyConfig),
                       ("contact_schema", ContactStudyConfig), ("bench_mpm_schema", MPMBenchConfig),
                       ("bench_render_schema", RenderBenchConfig), ("bench_scenes_schema", ScenesBenchConfig),
                       ("bench_overhead_schema", OverheadBenchConfig), ("bench_diffusion_schema", DiffusionBenchConfig)):
        store.store(name=name, node=node)
