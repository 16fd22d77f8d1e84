"""One gravity preload per body (:mod:`tasks.physics.gravity_preload`, :mod:`tasks.physics.mpm.preload`): a rollout that
puts the ``gravity_preload`` step's stored state into its solver is the same float32 bits as one that settles the body
itself, for the Dirichlet squeeze and for the force-driven one (whose push bounds its mass scale below the body's
load-free one, at which the preload runs), and a state of other inputs is not used."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from omegaconf import OmegaConf

from conf.schema import Config
from tasks.core.artifacts import read_artifact

INPUTS = ("object_model", "mpm_particles", "signal_smoothing", "force_coefficients", "contact_patches",
          "dirichlet_field", "material_oracle", "gravity_preload")


def _inputs(tmp_path, name: str, *extra: str):
    from flows.pipeline import run_object_local

    cfg = OmegaConf.merge(OmegaConf.structured(Config),
                          {"object": OmegaConf.load(f"conf/object/{name}.yaml"),
                           "mpm": OmegaConf.load("conf/mpm/default.yaml")},
                          OmegaConf.from_dotlist(["control.smoothing.frame_rate=20", "signal.duration=1.0", *extra]))
    refs = run_object_local(cfg, cfg.object, None, tmp_path, until="gravity_preload")
    a = {k: read_artifact(refs[k]) for k in INPUTS}
    args = ({**a["object_model"].arrays, **a["mpm_particles"].arrays},
            {**a["object_model"].attrs, **a["mpm_particles"].attrs, "name": name},
            a["dirichlet_field"].arrays, a["force_coefficients"]["force_coefficients"], a["contact_patches"].arrays,
            a["signal_smoothing"]["time"], a["material_oracle"].attrs["materials"], dict(cfg.mpm),
            dict(cfg.simulation))
    return args, a["gravity_preload"]


@pytest.fixture(scope="module")
def clay(tmp_path_factory):
    return _inputs(tmp_path_factory.mktemp("clay"), "clay")


@pytest.fixture(scope="module")
def ball(tmp_path_factory):
    return _inputs(tmp_path_factory.mktemp("ball"), "rubber_ball")


@pytest.mark.parametrize("body, boundary", [("clay", "dirichlet"), ("ball", "force")])
def test_a_rollout_from_the_stored_preload_is_the_rollout_that_preloads_itself(request, body, boundary):
    """Clay (von Mises: plastic strain and rotation warm starts) squeezed by its Dirichlet fingers, the rubber ball
    (a plane-stress wall with surface points) pushed by forces: every array and attribute of the rollout identical."""
    from tasks.physics.mpm_rollout import mpm_rollout
    from tasks.physics.preload_state import preload_from_artifact

    args, stored = request.getfixturevalue(body)
    state = preload_from_artifact(stored.arrays, stored.attrs)
    assert state is not None and state.figures.frames >= 2
    reused, reused_attrs = mpm_rollout(*args, boundary, state)
    own, own_attrs = mpm_rollout(*args, boundary)
    assert sorted(reused) == sorted(own)
    for key in own:
        assert np.array_equal(np.asarray(reused[key].data), np.asarray(own[key].data), equal_nan=True), key
    assert reused_attrs == own_attrs
    assert reused_attrs["gravity_preload"] == stored.attrs["gravity_preload"]
    if boundary == "force":  # the push bounds the scale: the squeeze runs at another scale than the preload
        assert own_attrs["mass_scale"] < stored.attrs["mass_scale"]


def test_a_preload_of_other_inputs_is_computed_again_with_a_note(clay):
    from tasks.physics.preload_state import preload_from_artifact
    from tasks.physics.rollout_scene import build_scene

    args, stored = clay
    state = preload_from_artifact(stored.arrays, stored.attrs)
    scene = build_scene(*args[:3], args[4], args[5], *args[6:], args[3], "dirichlet", replace(state, key="other"))
    assert any("computed again" in note for note in scene.notes)
    assert scene.preload == state.figures
    np.testing.assert_array_equal(scene.solver.deformation_gradients(), state.arrays["F"])


def test_a_scene_without_a_preload_stores_none_and_reads_back_none():
    from tasks.physics.preload_state import preload_arrays, preload_from_artifact

    arrays, attrs = preload_arrays(None)
    assert arrays == {} and attrs["preloaded"] is False
    assert preload_from_artifact(arrays, attrs) is None
