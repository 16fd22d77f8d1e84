"""Known answers of the renderable scene (tasks.render.scene): released-particle Gaussians, visibility, mask channel."""

import os

import numpy as np
import pytest
import torch

from tasks.render.cameras import orbit_cameras
from tasks.render.scene import (
    MAX_SURFACE_STRETCH,
    drawn_covariances,
    frame_scene,
    released_gaussians,
    released_visibility,
)
from tasks.render.splat import rasterization

torch.set_num_threads(int(os.environ.get("VIRSQUEEZER_TORCH_THREADS", "1")))


def _lattice(lo, hi, spacing: float) -> np.ndarray:
    axes = [np.arange(a, b + 1e-9, spacing) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def test_released_gaussians_take_sigma_from_the_particle_volume():
    volumes = np.array([1e-6, 8e-6, 2.7e-5])
    scene = released_gaussians(np.zeros((3, 3)), volumes, np.array([0.9, 0.5, 0.1]), 0.8, scale_factor=0.5)
    sigma = 0.5 * np.array([0.01, 0.02, 0.03])
    assert np.allclose(scene.covars[:, [0, 3, 5]], (sigma**2)[:, None]) and np.all(scene.covars[:, [1, 2, 4]] == 0)
    assert np.allclose(scene.colors, [[0.9, 0.5, 0.1, 1.0]] * 3) and np.allclose(scene.opacities, 0.8)
    assert all(a.dtype == np.float32 for a in scene)
    with pytest.raises(ValueError):
        released_gaussians(np.zeros((3, 3)), volumes[:2], np.ones(3), 0.8)


@pytest.mark.parametrize("k", [0.4, 0.6])
def test_released_gaussians_overlap_into_the_documented_density(k):
    """Particles on a lattice of spacing s = cbrt(volume): the summed density sum exp(-|x - p|^2 / (2 sigma^2)) is
    (2 pi)^(3/2) k^3 times theta(0)^3 at a particle and theta(1/2)^3 at a cell centre, theta(u) = 1 + 2 sum_m
    exp(-2 pi^2 k^2 m^2) cos(2 pi m u) (Poisson summation); |ripple| ~ 6 exp(-2 pi^2 k^2): < 0.5 % at k = 0.6."""
    s = 0.01
    positions = _lattice([-6 * s] * 3, [6 * s] * 3, s)
    scene = released_gaussians(positions, np.full(len(positions), s**3), np.ones(3), 1.0, scale_factor=k)
    sigma = np.sqrt(scene.covars[0, 0].astype(np.float64))
    assert sigma == pytest.approx(k * s, rel=1e-6)
    mean_density = (2 * np.pi) ** 1.5 * k**3

    def density(x):
        return np.exp(-np.sum((positions - x) ** 2, axis=1) / (2 * sigma**2)).sum() / mean_density

    terms = np.exp(-2 * np.pi**2 * k**2 * np.arange(1, 6) ** 2)
    assert density(np.zeros(3)) == pytest.approx((1 + 2 * terms.sum()) ** 3, rel=1e-6)
    at_centre = (1 + 2 * np.sum(terms * (-1.0) ** np.arange(1, 6))) ** 3
    assert density(np.full(3, s / 2)) == pytest.approx(at_centre, rel=1e-6)
    ripple = 6 * np.exp(-2 * np.pi**2 * k**2)
    assert abs(density(np.zeros(3)) - 1) == pytest.approx(ripple, rel=0.15)
    if k == 0.6:
        assert abs(density(np.zeros(3)) - 1) < 0.005


def test_released_visibility_starts_at_the_release_frame():
    released = np.array([True, False, True])
    visible = released_visibility(released, 2, 4)
    assert visible.shape == (4, 3)
    assert not visible[:2].any() and np.array_equal(visible[2:], [[True, False, True]] * 2)
    assert not released_visibility(released, None, 4).any()


def test_frame_scene_mask_channel_marks_released_material_only():
    """Camera at y = -2 m looking at +y. Surface: a thin opaque sheet at y = 0 over x < 0; released material: a slab
    beside it (x > 0) and a slab hidden behind the sheet (x < 0, y > 0). Mask = 1 where only released material is
    seen, 0 on the sheet (even with released material behind it); invisible particles are not drawn."""
    s_surf, s_part = 0.02, 0.03
    sheet = _lattice([-0.6, 0.0, -0.5], [-0.02, 0.0, 0.5], s_surf)
    sigma = 0.6 * s_surf
    sheet_covars = np.tile([sigma**2, 0.0, 0.0, (0.1 * sigma) ** 2, 0.0, sigma**2], (len(sheet), 1))
    beside = _lattice([0.05, -0.1, -0.5], [0.6, 0.1, 0.1], s_part)
    behind = _lattice([-0.6, 0.2, -0.5], [-0.05, 0.4, 0.5], s_part)
    hidden = _lattice([0.05, -0.1, 0.25], [0.6, 0.1, 0.5], s_part)   # not released yet
    particles = np.concatenate([beside, behind, hidden])
    visible = np.arange(len(particles)) < len(beside) + len(behind)
    scene = frame_scene(sheet, sheet_covars, np.full((len(sheet), 3), 0.8), np.full(len(sheet), 0.98), particles,
                        np.full(len(particles), s_part**3), visible, np.array([0.9, 0.3, 0.1]), 0.9)
    assert len(scene.means) == len(sheet) + visible.sum()
    assert np.all(scene.colors[: len(sheet), 3] == 0) and np.all(scene.colors[len(sheet):, 3] == 1)

    viewmats, Ks = orbit_cameras(np.zeros(3), 2.0, 1, 0.0, 40.0, 64, 48, azimuth0_deg=-90.0)
    image, alphas, _ = rasterization(torch.from_numpy(scene.means), None, None, torch.from_numpy(scene.opacities),
                                     torch.from_numpy(scene.colors), torch.from_numpy(viewmats).float(),
                                     torch.from_numpy(Ks).float(), 64, 48, covars=torch.from_numpy(scene.covars),
                                     backgrounds=torch.zeros(1, 4))
    mask, depth = image[0, ..., 3], image[0, ..., 4]
    left, right, above = (slice(10, 38), slice(6, 26)), (slice(22, 38), slice(38, 56)), (slice(5, 11), slice(38, 56))
    assert alphas[0, ..., 0][left].min() > 0.99 and alphas[0, ..., 0][right].min() > 0.99
    assert mask[right].min() > 0.99
    assert mask[left].max() < 0.01
    assert torch.allclose(depth[left], torch.tensor(2.0), atol=0.01)   # the sheet, not the slab behind it
    assert alphas[0, ..., 0][above].max() < 1e-6   # where only the unreleased particles are


def _sym6(c: np.ndarray) -> np.ndarray:
    return c[..., (0, 0, 0, 1, 1, 2), (0, 1, 2, 1, 2, 2)]


def _full(c6: np.ndarray) -> np.ndarray:
    i, j = (0, 0, 0, 1, 1, 2), (0, 1, 2, 1, 2, 2)
    out = np.zeros(c6.shape[:-1] + (3, 3))
    out[..., i, j] = c6
    out[..., j, i] = c6
    return out


def test_a_plastically_stretched_surface_gaussian_is_drawn_with_a_bounded_axis():
    """A flat surface Gaussian (rest scales 2, 2, 0.2 mm) stretched plastically 1000x along a rotated axis (a torn
    flake: F Sigma F^T has a 2 m axis) is drawn with its longest axis at MAX_SURFACE_STRETCH x 2 mm, along the same
    direction; its other axes and a mildly sheared Gaussian (within the bound) are drawn exactly as simulated.
    Rendered, the flake covers a few pixels instead of a streak across the image."""
    rest = np.array([[2e-3, 2e-3, 2e-4], [2e-3, 2e-3, 2e-4]])
    c, s_ = np.cos(0.4), np.sin(0.4)
    R = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
    streak = R @ np.diag([1000.0, 1.0, 0.5]) @ R.T
    sheared = np.array([[1.5, 0.4, 0.0], [0.0, 1.0, 0.0], [0.0, 0.1, 0.9]])
    cov = np.stack([F @ np.diag(r**2) @ F.T for F, r in zip([streak, sheared], rest)])
    drawn = _full(drawn_covariances(_sym6(cov)[None], rest)[0].astype(np.float64))
    w, q = np.linalg.eigh(drawn[0])
    assert np.sqrt(w[-1]) == pytest.approx(MAX_SURFACE_STRETCH * 2e-3, rel=1e-4)  # 8 mm, not 2 m
    assert abs(q[:, -1] @ R[:, 0]) == pytest.approx(1.0, abs=1e-6)  # still along the stretch
    assert np.sqrt(w[:2]) == pytest.approx([1e-4, 2e-3], rel=1e-4)  # the untouched axes
    assert np.allclose(drawn[1], cov[1], rtol=1e-5, atol=1e-12)  # within the bound: as simulated
    with pytest.raises(ValueError, match="rest_scales"):
        drawn_covariances(_sym6(cov), rest[:1])

    viewmats, Ks = orbit_cameras(np.zeros(3), 0.5, 1, 0.0, 40.0, 64, 64, azimuth0_deg=-90.0)  # edge-on
    footprint = []
    for covars in (_sym6(cov[:1]), drawn_covariances(_sym6(cov[:1]), rest[:1])):
        _, alphas, _ = rasterization(torch.zeros(1, 3), None, None, torch.ones(1), torch.ones(1, 3),
                                     torch.from_numpy(viewmats).float(), torch.from_numpy(Ks).float(), 64, 64,
                                     covars=torch.from_numpy(np.asarray(covars, np.float32)))
        footprint.append(int((alphas[0, ..., 0] > 0.01).sum()))
    assert footprint[0] > 60 and footprint[1] < 30, footprint  # a streak through the image; a small splat
