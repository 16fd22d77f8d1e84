"""The render -> conditions -> effect -> refinement (eq. 7) chain on synthetic scenes with known answers."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from tasks.generation.appearance_refinement import FrozenFrames, ReleasedAppearance, refine, render_frame
from tasks.generation.effect import physics_effect
from tasks.render.cameras import orbit_cameras
from tasks.render.conditions import refine_mask
from tasks.render.gbuffer import render_gbuffer
from tasks.render.scene import released_appearance

W = H = 48


pytestmark = pytest.mark.usefixtures("torch_one_thread")


def _wall_and_blob(n_frames: int = 2):
    """A vertical wall of flat grey surface Gaussians at x = -0.02 m, and 9 released particles on a 3 x 3 grid of
    6 mm spacing in the plane x = 0 in front of it (seen from cameras on the +x side: every particle visible)."""
    yz = np.stack(np.meshgrid(np.linspace(-0.04, 0.04, 17), np.linspace(-0.04, 0.04, 17)), -1).reshape(-1, 2)
    surface = np.column_stack([np.full(len(yz), -0.02), yz])
    cov = np.zeros((len(surface), 6))
    cov[:, [0, 3, 5]] = [1e-8, 3e-5, 3e-5]  # flat in x, 5.5 mm across
    g = np.linspace(-0.006, 0.006, 3)
    blob = np.column_stack([np.zeros(9), np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)])
    return (np.repeat(surface[None], n_frames, 0), np.repeat(cov[None], n_frames, 0),
            np.full((len(surface), 3), 0.5), np.full(len(surface), 0.99), np.repeat(blob[None], n_frames, 0),
            np.full(len(blob), (0.006) ** 3))


def _cameras(n_views=2):
    """n_views cameras on the +x side of the wall, 0.15 m from the blob, between azimuths -30 and +30 degrees."""
    rigs = [orbit_cameras(np.zeros(3), 0.15, 1, 10.0, 40.0, W, H, azimuth0_deg=a)
            for a in np.linspace(-30.0, 30.0, n_views)]
    return np.concatenate([r[0] for r in rigs]), np.concatenate([r[1] for r in rigs])


def test_gbuffer_mask_is_the_released_material_and_surface_depth_ignores_it():
    sp, sc, scol, sop, pp, pv = _wall_and_blob()
    viewmats, Ks = _cameras()
    visible = np.array([[False] * len(pv), [True] * len(pv)])  # released in frame 1 only
    g = render_gbuffer(sp, sc, scol, sop, pp, pv, visible, np.array([0.9, 0.3, 0.0]), 0.9, viewmats, Ks, W, H,
                       np.array([1.0, 1.0, 1.0]), 0.01, torch.device("cpu"))
    assert g["mask"][:, 0].max() == 0.0  # nothing released yet
    centre = g["mask"][:, 1, H // 2, W // 2]
    assert np.all(centre > 0.5)  # the blob covers the image centre
    # the object alone lies behind the blob: its depth at the centre is the wall's, farther than the blob
    assert np.all(g["surface_depth"][:, 1, H // 2, W // 2] > g["depth"][:, 1, H // 2, W // 2] + 0.005)
    empty = g["alpha"][:, 1] <= 1e-3  # nothing at all is drawn there, so the object alone is not either
    assert empty.any() and np.isinf(g["surface_depth"][:, 1][empty]).all()
    # a frame without release: surface depth is the rendered depth
    np.testing.assert_array_equal(g["surface_depth"][:, 0][g["alpha"][:, 0] > 1e-3],
                                  g["depth"][:, 0][g["alpha"][:, 0] > 1e-3])


def test_physics_effect_leaves_every_pixel_outside_the_refined_mask_bit_identical():
    sp, sc, scol, sop, pp, pv = _wall_and_blob()
    viewmats, Ks = _cameras()
    visible = np.ones((2, len(pv)), bool)
    g = render_gbuffer(sp, sc, scol, sop, pp, pv, visible, np.array([0.9, 0.3, 0.0]), 0.9, viewmats, Ks, W, H,
                       np.array([1.0, 1.0, 1.0]), 0.01, torch.device("cpu"))
    mask = np.stack([refine_mask(g["mask"][v], 1, 1) for v in range(2)])
    out = physics_effect(g["rgb"], g["surface_depth"], mask, pp, np.full(len(pv), 0.004), visible, viewmats, Ks,
                         "cola_spray", seed=0)
    np.testing.assert_array_equal(out[~mask], g["rgb"][~mask])
    assert np.abs(out[mask] - g["rgb"][mask]).max() > 0.05  # inside, the cola is drawn


def test_refinement_recovers_a_known_colour_and_opacity_and_keeps_the_surface_frozen():
    """Frame 0 shows the particles over the grey wall, frame 1 over the white background (the wall moved out of
    view): colour and opacity are then both determined (over one background they trade off)."""
    sp, sc, scol, sop, pp, pv = _wall_and_blob(n_frames=2)
    sp[1, :, 1] += 1.0
    viewmats, Ks = (torch.as_tensor(a, dtype=torch.float32) for a in _cameras(3))
    def t(a):
        return torch.as_tensor(np.asarray(a), dtype=torch.float32)

    frozen = FrozenFrames(t(sp), t(sc), t(scol), t(sop), t(pp), torch.ones((2, len(pv)), dtype=torch.bool))
    before = [x.clone() for x in (frozen.surface_means, frozen.surface_covars, frozen.surface_colors,
                                  frozen.surface_opacities)]
    scale = np.full((len(pv), 3), 0.6 * 0.006)
    truth = ReleasedAppearance(np.tile([0.2, 0.6, 0.3], (len(pv), 1)), np.full(len(pv), 0.8), scale)
    background = torch.ones(3)
    with torch.no_grad():  # (view, frame, y, x, 3)
        target = torch.stack([render_frame(frozen, truth, f, viewmats, Ks, W, H, background) for f in (0, 1)], 1)
    weights = torch.ones(target.shape[:-1])
    theta = ReleasedAppearance(np.tile([0.8, 0.4, 0.1], (len(pv), 1)), np.full(len(pv), 0.4), scale)
    curve = refine(frozen, theta, target, weights, viewmats, Ks, background, [0, 1], [0, 1], iterations=100,
                   lr=0.1, samples=2, seed=0)
    colors, opacities, _ = (x.detach().numpy() for x in theta.values())
    assert curve[-1] < 0.2 * curve[0]
    np.testing.assert_allclose(colors.mean(axis=0), [0.2, 0.6, 0.3], atol=0.05)
    assert abs(opacities.mean() - 0.8) < 0.1
    for a, b in zip(before, (frozen.surface_means, frozen.surface_covars, frozen.surface_colors,
                             frozen.surface_opacities)):
        assert torch.equal(a, b) and not b.requires_grad


def test_released_appearance_is_found_by_a_word_of_the_interior_name():
    render = {"released": {"cola": {"color": [0.1, 0.0, 0.0], "opacity": 0.9, "effect": "liquid"},
                           "fibrefill": {"color": [0.9, 0.9, 0.9], "opacity": 0.9, "effect": "stuffing"}},
              "released_default": {"color": [0.5, 0.5, 0.5], "opacity": 0.5, "effect": "liquid"}}
    assert released_appearance(render, "Regular cola")["color"] == [0.1, 0.0, 0.0]
    assert released_appearance(render, "loose polyester fibrefill (torn out)")["effect"] == "stuffing"
    assert released_appearance(render, "honey")["opacity"] == 0.5


def test_ply_sequence_round_trips_the_deformed_covariances(tmp_path):
    from tasks.control.gaussian_ply import read_gaussian_ply
    from tasks.generation.ply_sequence import covariance_to_scale_rotation, write_ply_sequence

    rng = np.random.default_rng(0)
    A = rng.normal(size=(5, 3, 3)) * 0.01
    full = A @ A.transpose(0, 2, 1) + 1e-6 * np.eye(3)  # symmetric positive definite, like F Sigma F^T
    cov6 = full[:, [0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]]
    scales, quats = covariance_to_scale_rotation(cov6)
    from scipy.spatial.transform import Rotation

    R = Rotation.from_quat(np.concatenate([quats[:, 1:], quats[:, :1]], 1)).as_matrix()
    np.testing.assert_allclose(R @ (scales[:, :, None] ** 2 * R.transpose(0, 2, 1)), full, atol=1e-12)
    pos = rng.normal(size=(2, 5, 3)) * 0.02
    released = rng.normal(size=(2, 3, 3)) * 0.02
    visible = np.array([[False, False, False], [True, False, True]])
    paths = write_ply_sequence(tmp_path, pos, np.repeat(cov6[None], 2, 0), np.full((5, 3), 0.4), np.full(5, 0.9),
                               released, visible, np.full((3, 3), 0.7), np.full(3, 0.5), np.full((3, 3), 0.002),
                               np.array([0, 2]))
    assert [p.name for p in paths] == ["frame_0000.ply", "frame_0002.ply"]
    first, second = read_gaussian_ply(paths[0]), read_gaussian_ply(paths[1])
    assert len(first["means"]) == 5 and len(second["means"]) == 7  # the surface + the 2 visible particles
    np.testing.assert_allclose(second["means"][5:], released[1][[0, 2]], atol=1e-7)
    np.testing.assert_allclose(first["scales"], scales, rtol=1e-5)
