"""Known answers of the Gaussian splatting renderer (tasks.render.splat) on both compositing backends."""

import math
import os

import numpy as np
import pytest
import torch

from tasks.render import splat_warp
from tasks.render.cameras import distance_for_object, orbit_cameras, project_points
from tasks.render.splat import rasterization
from tasks.render.splat_projection import project_gaussians, quat_scale_to_covar
from tasks.render.splat_warp_projection import project_gaussians_warp

torch.set_num_threads(int(os.environ.get("VIRSQUEEZER_TORCH_THREADS", "1")))

BACKENDS = ("torch", "warp")
FOCAL, WIDTH, HEIGHT = 100.0, 64, 48


@pytest.fixture(params=("torch", "warp", "warp-scalar"))
def backend(request, monkeypatch):
    """The backend a test renders with: the torch reference, the Warp backend (on the CPU its lanes compositor) and
    "warp-scalar", the Warp backend with its pure-Warp compositing kernels (CUDA's) on the CPU."""
    if request.param == "warp-scalar":
        monkeypatch.setattr(splat_warp, "COMPOSITOR", "scalar")
        return "warp"
    return request.param


@pytest.fixture(params=("auto", "scalar"))
def compositor(request, monkeypatch):
    """The Warp backend's compositor on the CPU: "auto" (lanes) or "scalar" (the pure-Warp kernels CUDA runs)."""
    monkeypatch.setattr(splat_warp, "COMPOSITOR", request.param)
    return request.param


def _camera(n_views: int = 1, dtype=torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """Identity extrinsics (camera at the origin looking along +z) and a pinhole with centre (32, 24) px."""
    K = torch.tensor([[FOCAL, 0.0, WIDTH / 2], [0.0, FOCAL, HEIGHT / 2], [0.0, 0.0, 1.0]], dtype=dtype)
    return torch.eye(4, dtype=dtype).repeat(n_views, 1, 1), K.repeat(n_views, 1, 1)


def _isotropic(n: int, sigma: float, dtype=torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    return torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=dtype).repeat(n, 1), torch.full((n, 3), sigma, dtype=dtype)


def _at_pixel_centre(x_px: float, y_px: float, depth: float) -> list[float]:
    """The world point (identity camera) that projects to the pixel centre (x_px + 0.5, y_px + 0.5) at depth z."""
    return [(x_px + 0.5 - WIDTH / 2) * depth / FOCAL, (y_px + 0.5 - HEIGHT / 2) * depth / FOCAL, depth]


def test_single_gaussian_renders_its_analytic_footprint(backend):
    """alpha(x) = o exp(-0.5 d^T cov2d^-1 d), cov2d = (f sigma / z)^2 (I + off-axis term) + eps2d I; a quadratic fit
    of log alpha recovers the projected mean, the pixel sigmas and the peak (= opacity)."""
    z, sigma, opacity = 2.0, 0.05, 0.8
    mean = torch.tensor([[0.0123, -0.0071, z]])
    quats, scales = _isotropic(1, sigma)
    viewmats, Ks = _camera()
    _, alphas, meta = rasterization(mean, quats, scales, torch.tensor([opacity]), torch.ones(1, 3), viewmats, Ks,
                                    WIDTH, HEIGHT, render_mode="RGB", backend=backend)
    a = alphas[0, :, :, 0].double()
    ys, xs = torch.nonzero(a > 0.05, as_tuple=True)
    px, py = xs.double() + 0.5, ys.double() + 0.5
    design = torch.stack([torch.ones_like(px), px, py, px * px, px * py, py * py], dim=1)
    c = torch.linalg.lstsq(design, torch.log(a[ys, xs])[:, None]).solution[:, 0]
    precision = -2 * torch.tensor([[c[3], c[4] / 2], [c[4] / 2, c[5]]])
    centre = torch.linalg.solve(precision, c[1:3])
    cov2d = torch.linalg.inv(precision)
    peak = torch.exp(c[0] + 0.5 * centre @ precision @ centre)

    x, y = mean[0, 0].item(), mean[0, 1].item()
    expected_centre = torch.tensor([FOCAL * x / z + WIDTH / 2, FOCAL * y / z + HEIGHT / 2], dtype=torch.float64)
    assert torch.allclose(meta["means2d"][0, 0].double(), expected_centre, atol=1e-4)
    assert torch.max(torch.abs(centre - expected_centre)) < 0.05
    s2 = (FOCAL * sigma / z) ** 2
    expected_var = torch.tensor([s2 * (1 + (x / z) ** 2) + 0.3, s2 * (1 + (y / z) ** 2) + 0.3], dtype=torch.float64)
    assert torch.allclose(torch.diagonal(cov2d), expected_var, rtol=1e-3)
    assert abs(cov2d[0, 1] - s2 * x * y / z**2) < 1e-3
    assert abs(peak.item() - opacity) < 1e-4
    assert meta["radii"][0, 0] == math.ceil(3 * math.sqrt(expected_var.max().item()))


def test_two_gaussians_composite_front_to_back_in_any_input_order(backend):
    """At the shared centre pixel: alpha = 1 - (1 - a1)(1 - a2), colour = a1 c1 + (1 - a1) a2 c2, expected depth =
    (a1 z1 + (1 - a1) a2 z2) / alpha; swapping the input order changes nothing."""
    a1, a2, z1, z2 = 0.7, 0.9, 2.0, 3.0
    means = torch.tensor([_at_pixel_centre(30, 20, z1), _at_pixel_centre(30, 20, z2)])
    quats, scales = _isotropic(2, 0.03)
    colors = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    opacities = torch.tensor([a1, a2])
    viewmats, Ks = _camera()
    image, alphas, _ = rasterization(means, quats, scales, opacities, colors, viewmats, Ks, WIDTH, HEIGHT,
                                     backend=backend)
    alpha = 1 - (1 - a1) * (1 - a2)
    assert alphas[0, 20, 30, 0].item() == pytest.approx(alpha, abs=1e-6)
    expected = torch.tensor([a1, 0.0, (1 - a1) * a2, (a1 * z1 + (1 - a1) * a2 * z2) / alpha])
    assert torch.allclose(image[0, 20, 30], expected, atol=1e-5)
    assert image[0, 20, 30, 0] > image[0, 20, 30, 2]   # the front colour dominates

    flipped, flipped_alphas, _ = rasterization(means.flip(0), quats, scales.flip(0), opacities.flip(0),
                                               colors.flip(0), viewmats, Ks, WIDTH, HEIGHT, backend=backend)
    assert torch.equal(flipped, image) and torch.equal(flipped_alphas, alphas)


def test_a_pixel_stops_before_its_transmittance_drops_below_1e_4(backend):
    """Five stacked Gaussians of peak alpha 0.95 at one pixel: T = 0.05, 0.0025, 1.25e-4, then 6.25e-6 < 1e-4, so the
    pixel stops at the 4th, which is left out with everything behind it: alpha = 1 - 1.25e-4, the colour sums the
    first three, and the 4th and 5th colours get zero gradient while the 3rd gets its weight 0.95 * 0.0025."""
    depths = [2.0, 2.1, 2.2, 2.3, 2.4]
    means = torch.tensor([_at_pixel_centre(10, 12, z) for z in depths])
    quats, scales = _isotropic(5, 0.01)
    colors = torch.eye(5)[:, :4].contiguous().requires_grad_(True)   # Gaussian i lights channel i (the 5th: none)
    viewmats, Ks = _camera()
    image, alphas, _ = rasterization(means, quats, scales, torch.full((5,), 0.95), colors, viewmats, Ks, WIDTH,
                                     HEIGHT, render_mode="RGB", backend=backend)
    assert alphas[0, 12, 10, 0].item() == pytest.approx(1 - 0.05**3, abs=1e-7)
    assert torch.allclose(image[0, 12, 10], torch.tensor([0.95, 0.95 * 0.05, 0.95 * 0.05**2, 0.0]), atol=1e-7)
    image[0, 12, 10, 2].backward()
    assert colors.grad[2, 2].item() == pytest.approx(0.95 * 0.05**2, rel=1e-5)
    assert torch.all(colors.grad[3:] == 0)


def test_fronto_parallel_plane_renders_its_depth(backend):
    """A plane of overlapping Gaussians at z = 2.5 m: expected depth = 2.5 m wherever alpha > 0.5."""
    z, spacing = 2.5, 0.04
    grid = torch.arange(-20, 21, dtype=torch.float32) * spacing
    gx, gy = torch.meshgrid(grid, grid, indexing="xy")
    means = torch.stack([gx.flatten(), gy.flatten(), torch.full((gx.numel(),), z)], dim=1)
    quats, scales = _isotropic(len(means), 0.6 * spacing)
    viewmats, Ks = _camera()
    image, alphas, _ = rasterization(means, quats, scales, torch.full((len(means),), 0.6), torch.ones(len(means), 3),
                                     viewmats, Ks, WIDTH, HEIGHT, backend=backend)
    covered = alphas[..., 0] > 0.5
    assert covered.float().mean() > 0.9
    assert torch.max(torch.abs(image[..., 3][covered] / z - 1)) < 1e-4


def _tiny_scene(dtype):
    """Three large Gaussians (5-7 px sigma: their boxes and alpha >= 1/255 regions cover the whole 12 x 10 image,
    so the loss is smooth) seen by two cameras."""
    g = torch.Generator().manual_seed(3)
    means = torch.tensor([[0.02, -0.01, 2.0], [-0.03, 0.02, 2.4], [0.0, 0.03, 2.8]], dtype=dtype)
    quats = torch.nn.functional.normalize(torch.randn(3, 4, generator=g, dtype=dtype), dim=1)
    scales = torch.tensor([[0.6, 0.45, 0.5], [0.5, 0.7, 0.4], [0.65, 0.5, 0.6]], dtype=dtype)
    opacities = torch.tensor([0.5, 0.6, 0.7], dtype=dtype)
    colors = torch.rand(3, 4, generator=g, dtype=dtype)
    K = torch.tensor([[20.0, 0.0, 6.0], [0.0, 20.0, 5.0], [0.0, 0.0, 1.0]], dtype=dtype)
    viewmats = torch.eye(4, dtype=dtype).repeat(2, 1, 1)
    viewmats[1, 0, 3] = 0.05
    weights = torch.rand(2, 10, 12, 6, generator=g, dtype=dtype)
    return [means, quats, scales, opacities, colors], viewmats, K.repeat(2, 1, 1), weights


def _loss(params, viewmats, Ks, weights, backend, use_covars):
    means, quats, scales, opacities, colors = params[:5]
    covars = params[5] if use_covars else None
    image, alphas, _ = rasterization(means, None if use_covars else quats, None if use_covars else scales,
                                     opacities, colors, viewmats, Ks, 12, 10, covars=covars, backend=backend)
    return (torch.cat([image, alphas], dim=-1) * weights).sum()


@pytest.mark.parametrize("use_covars", [False, True], ids=["quats_scales", "covars"])
def test_gradients_match_central_differences(backend, use_covars):
    """d loss / d (means, quats, scales | covars, opacities, colors) against central differences: float64 on the
    torch backend; the warp backend computes in float32, so its differences are noisier."""
    dtype, step, tol = (torch.float64, 1e-6, 1e-6) if backend == "torch" else (torch.float32, 2e-3, 1e-2)
    params, viewmats, Ks, weights = _tiny_scene(torch.float64)
    if use_covars:
        params.append(quat_scale_to_covar(params[1], params[2]))
    params = [p.to(dtype).requires_grad_(True) for p in params]
    viewmats, Ks, weights = viewmats.to(dtype), Ks.to(dtype), weights.to(dtype)
    _loss(params, viewmats, Ks, weights, backend, use_covars).backward()
    checked = [0, 3, 4, 5] if use_covars else [0, 1, 2, 3, 4]
    for i in checked:
        numeric = torch.zeros_like(params[i])
        for j in range(params[i].numel()):
            with torch.no_grad():
                flat = params[i].view(-1)
                flat[j] += step
                up = _loss(params, viewmats, Ks, weights, backend, use_covars)
                flat[j] -= 2 * step
                down = _loss(params, viewmats, Ks, weights, backend, use_covars)
                flat[j] += step
            numeric.view(-1)[j] = (up - down) / (2 * step)
        error = torch.linalg.norm(params[i].grad - numeric) / torch.linalg.norm(numeric)
        assert error < tol, f"parameter {i}: relative error {error:.2e}"


def _random_scene(n: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    means = torch.cat([torch.rand(n, 2, generator=g) - 0.5, 2.0 + torch.rand(n, 1, generator=g)], dim=1)
    quats = torch.randn(n, 4, generator=g)
    scales = 0.005 + 0.04 * torch.rand(n, 3, generator=g)
    opacities = 0.05 + 0.94 * torch.rand(n, generator=g)
    colors = torch.rand(n, 4, generator=g)
    return [means, quats, scales, opacities, colors]


def test_backends_agree_on_a_random_scene(compositor):
    """Warp vs the torch reference: images to 1e-5, gradients of a random linear loss to 1e-4 (relative norm)."""
    params = _random_scene(400, seed=0)
    viewmats, Ks = _camera(2)
    viewmats[1, :3, 3] = torch.tensor([0.1, -0.05, 0.2])
    backgrounds = torch.tensor([[0.1, 0.2, 0.3, 0.0], [1.0, 1.0, 1.0, 0.0]])
    weights = torch.rand(2, HEIGHT, WIDTH, 6, generator=torch.Generator().manual_seed(1))
    outputs = {}
    for backend in BACKENDS:
        leaves = [p.clone().requires_grad_(True) for p in params]
        image, alphas, _ = rasterization(*leaves, viewmats, Ks, WIDTH, HEIGHT, backgrounds=backgrounds,
                                         render_mode="RGB+D", backend=backend)
        (torch.cat([image, alphas], dim=-1) * weights).sum().backward()
        outputs[backend] = (image.detach(), alphas.detach(), [p.grad for p in leaves])
    (ref_image, ref_alphas, ref_grads), (image, alphas, grads) = outputs["torch"], outputs["warp"]
    assert ref_alphas.max() > 0.99 and (ref_alphas < 1e-3).any()   # opaque and empty pixels both present
    assert torch.max(torch.abs(image[..., :4] - ref_image[..., :4])) < 1e-5
    assert torch.max(torch.abs(alphas - ref_alphas)) < 1e-5
    assert torch.max(torch.abs(image[..., 4] - ref_image[..., 4])) < 1e-5 * 3.0   # accumulated depth, m
    for name, grad, ref in zip(("means", "quats", "scales", "opacities", "colors"), grads, ref_grads):
        assert torch.linalg.norm(grad - ref) < 1e-4 * torch.linalg.norm(ref), name


def test_long_spans_and_ragged_rows_agree_with_the_reference(compositor):
    """Spans longer than a block of lanes (16, 32 px and whole rows), Gaussians across the left and right image
    edges and a width that is no multiple of 16 (37 px; the lanes compositor pads its planes): the Warp backend
    against the torch reference, images to 1e-5 and gradients of a random linear loss to 1e-4 (relative norm)."""
    width, height, z = 37, 11, 2.0
    centres = [(18.0, 5.0, 0.02), (36.5, 3.0, 0.06), (-0.5, 8.0, 0.04), (9.0, 1.0, 0.12), (30.0, 9.5, 0.3)]
    depths = z + 0.1 * torch.arange(len(centres))   # distinct depths
    means = torch.tensor([[(x + 0.5 - width / 2) * d / FOCAL, (y + 0.5 - height / 2) * d / FOCAL, d]
                          for (x, y, _), d in zip(centres, depths.tolist())])
    scales = torch.tensor([[s, 0.6 * s, s] for _, _, s in centres])
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.9, 0.0, 0.0, 0.3], [1.0, 0.0, 0.0, 0.0], [0.8, 0.1, 0.0, -0.5],
                          [1.0, 0.0, 0.0, 0.0]])
    opacities = torch.tensor([0.9, 0.7, 0.95, 0.5, 0.3])
    colors = torch.rand(len(centres), 4, generator=torch.Generator().manual_seed(3))
    K = torch.tensor([[[FOCAL, 0.0, width / 2], [0.0, FOCAL, height / 2], [0.0, 0.0, 1.0]]])
    weights = torch.rand(1, height, width, 6, generator=torch.Generator().manual_seed(4))
    outputs = {}
    for backend in BACKENDS:
        leaves = [t.clone().requires_grad_(True) for t in (means, quats, scales, opacities, colors)]
        image, alphas, meta = rasterization(*leaves, torch.eye(4)[None], K, width, height, render_mode="RGB+ED",
                                            backend=backend)
        (torch.cat([image, alphas], dim=-1) * weights).sum().backward()
        outputs[backend] = (image.detach(), alphas.detach(), [t.grad for t in leaves], meta["radii"])
    (ref_image, ref_alphas, ref_grads, radii), (image, alphas, grads, _) = outputs["torch"], outputs["warp"]
    assert radii.max() > 20 and ref_alphas[0, :, 0, 0].max() > 0.5 and ref_alphas[0, :, -1, 0].max() > 0.5
    assert torch.max(torch.abs(image - ref_image)) < 1e-5 and torch.max(torch.abs(alphas - ref_alphas)) < 1e-5
    for name, grad, ref in zip(("means", "quats", "scales", "opacities", "colors"), grads, ref_grads):
        assert torch.linalg.norm(grad - ref) < 1e-4 * torch.linalg.norm(ref), name


@pytest.mark.parametrize("render_mode", ["RGB+ED", "ED"])
def test_backends_agree_on_covariances_and_per_camera_colours(render_mode, compositor):
    """The Warp frame's other inputs against the torch reference: covars (its covariance adjoint), colours per camera
    (C, N, D) (its per-instance records and their scatter) and, with "ED", the depth alone (no colour channel):
    images to 1e-5 (expected depth: 1e-4 m), gradients of a random linear loss to 1e-4 (relative norm)."""
    means, quats, scales, opacities, colors = _random_scene(300, seed=6)
    covars = quat_scale_to_covar(quats, scales)
    viewmats, Ks = _camera(2)
    viewmats[1, :3, 3] = torch.tensor([-0.1, 0.05, 0.1])
    colors = torch.stack([colors, colors.flip(0)])   # (C, N, D)
    outputs = {}
    for backend in BACKENDS:
        leaves = [t.clone().requires_grad_(True) for t in (means, covars, opacities, colors)]
        image, alphas, _ = rasterization(leaves[0], None, None, leaves[2], leaves[3], viewmats, Ks, WIDTH, HEIGHT,
                                         covars=leaves[1], render_mode=render_mode, backend=backend)
        weights = torch.rand(image.shape, generator=torch.Generator().manual_seed(2))
        ((image * weights).sum() + alphas.sum()).backward()
        outputs[backend] = (image.detach(), alphas.detach(), [t.grad for t in leaves])
    (ref_image, ref_alphas, ref_grads), (image, alphas, grads) = outputs["torch"], outputs["warp"]
    assert image.shape[-1] == (1 if render_mode == "ED" else 5) and ref_alphas.max() > 0.99
    assert render_mode == "ED" or torch.max(torch.abs(image[..., :-1] - ref_image[..., :-1])) < 1e-5
    assert torch.max(torch.abs(image[..., -1] - ref_image[..., -1])[ref_alphas[..., 0] > 0.01]) < 1e-4
    assert torch.max(torch.abs(alphas - ref_alphas)) < 1e-5
    checked = zip(("means", "covars", "opacities", "colors"), grads, ref_grads)
    for name, grad, ref in (list(checked)[:3] if render_mode == "ED" else checked):
        assert torch.linalg.norm(grad - ref) < 1e-4 * torch.linalg.norm(ref), name


def test_covariance_input_culling_and_modes(backend):
    """covars (N, 6) render exactly like quats + scales; a Gaussian behind the near plane is culled and gets a zero
    gradient; "D" is the accumulated depth, i.e. "ED" times alpha."""
    params = _random_scene(50, seed=2)
    params[0][0, 2] = -1.0   # behind the camera
    means, quats, scales, opacities, colors = [p.requires_grad_(True) for p in params]
    viewmats, Ks = _camera()
    image, alphas, meta = rasterization(means, quats, scales, opacities, colors, viewmats, Ks, WIDTH, HEIGHT,
                                        backend=backend)
    covars = quat_scale_to_covar(quats, scales)
    image_c, _, _ = rasterization(means, None, None, opacities, colors, viewmats, Ks, WIDTH, HEIGHT, covars=covars,
                                  backend=backend)
    assert torch.allclose(image[..., :4], image_c[..., :4], atol=1e-6)   # colours; the expected depth (m) divides
    assert torch.allclose(image[..., 4], image_c[..., 4], atol=1e-4)     # by alpha, so faint pixels amplify rounding
    assert meta["radii"][0, 0] == 0 and 0 not in meta["gaussian_ids"]
    image.sum().backward()
    assert torch.all(means.grad[0] == 0) and torch.all(torch.isfinite(means.grad))
    depth, _, _ = rasterization(means, quats, scales, opacities, colors, viewmats, Ks, WIDTH, HEIGHT,
                                render_mode="D", backend=backend)
    assert torch.allclose(depth[..., 0], (image[..., -1] * alphas[..., 0]).detach(), atol=1e-5)


def test_a_frame_with_every_gaussian_culled_is_its_background(backend):
    """Gaussians behind the camera and off screen draw nothing: the background everywhere, alpha 0, zero gradients."""
    means = torch.tensor([[0.0, 0.0, -1.0], [50.0, 0.0, 2.0]], requires_grad=True)
    quats, scales = _isotropic(2, 0.01)
    viewmats, Ks = _camera()
    image, alphas, meta = rasterization(means, quats, scales, torch.ones(2), torch.ones(2, 3), viewmats, Ks, WIDTH,
                                        HEIGHT, backgrounds=torch.tensor([[0.2, 0.4, 0.6]]), render_mode="RGB",
                                        backend=backend)
    assert torch.equal(image[0], torch.tensor([0.2, 0.4, 0.6]).expand(HEIGHT, WIDTH, 3))
    assert torch.all(alphas == 0) and len(meta["gaussian_ids"]) == 0
    image.sum().backward()
    assert torch.all(means.grad == 0)


def test_bad_inputs_are_named():
    means, quats, scales, opacities, colors = _random_scene(5, seed=4)
    viewmats, Ks = _camera()
    with pytest.raises(ValueError, match="covars"):
        rasterization(means, None, None, opacities, colors, viewmats, Ks, WIDTH, HEIGHT)
    with pytest.raises(ValueError, match="opacities"):
        rasterization(means, quats, scales, opacities[:3], colors, viewmats, Ks, WIDTH, HEIGHT)
    with pytest.raises(ValueError, match="render_mode"):
        rasterization(means, quats, scales, opacities, colors, viewmats, Ks, WIDTH, HEIGHT, render_mode="RGBD")
    with pytest.raises(ValueError, match="backend"):
        rasterization(means, quats, scales, opacities, colors, viewmats, Ks, WIDTH, HEIGHT, backend="cuda")


@pytest.mark.parametrize("project", [project_gaussians, project_gaussians_warp], ids=BACKENDS)
def test_projection_matches_gsplat_reference(project):
    """Our EWA projections against gsplat's pure-torch ``_fully_fused_projection`` (skipped without gsplat; its
    radii are per axis, 3.33 sigma, ours 3 sqrt(lambda_max), so only the culling of central Gaussians is compared)."""
    gsplat_impl = pytest.importorskip("gsplat.cuda._torch_impl")
    means, quats, scales, _, _ = _random_scene(300, seed=5)
    viewmats, Ks = _camera(2)
    viewmats[1, :3, 3] = torch.tensor([0.2, 0.1, 0.3])
    covars = quat_scale_to_covar(quats, scales)
    ours = project(means, covars, viewmats, Ks, WIDTH, HEIGHT)
    covar_matrices, _ = gsplat_impl._quat_scale_to_covar_preci(quats, scales, compute_preci=False)
    radii, means2d, depths, conics, _ = gsplat_impl._fully_fused_projection(means, covar_matrices, viewmats, Ks,
                                                                            WIDTH, HEIGHT)
    drawn = (ours.radii > 0) & (radii > 0).all(-1)
    assert drawn.sum() > 300
    assert torch.max(torch.abs(ours.means2d - means2d)[drawn]) < 1e-4
    assert torch.allclose(ours.depths, depths, atol=1e-6)
    assert torch.allclose(ours.conics[drawn], conics[drawn], rtol=1e-4, atol=1e-6)
    inside = ((means2d[..., 0] > 8) & (means2d[..., 0] < WIDTH - 8) & (means2d[..., 1] > 8)
              & (means2d[..., 1] < HEIGHT - 8))
    assert torch.equal((ours.radii > 0)[inside], (radii > 0).all(-1)[inside])


def test_orbit_cameras_look_at_the_centre_from_even_azimuths():
    center, radius, n_views, elevation = np.array([0.1, -0.2, 0.3]), 0.8, 6, 25.0
    viewmats, Ks = orbit_cameras(center, radius, n_views, elevation, 40.0, 96, 64, azimuth0_deg=10.0)
    positions = np.stack([-v[:3, :3].T @ v[:3, 3] for v in viewmats])
    offsets = positions - center
    assert np.allclose(np.linalg.norm(offsets, axis=1), radius)
    assert np.allclose(np.degrees(np.arcsin(offsets[:, 2] / radius)), elevation)
    azimuths = np.degrees(np.arctan2(offsets[:, 1], offsets[:, 0]))
    assert np.allclose((azimuths - 10.0 - 60.0 * np.arange(n_views) + 180) % 360 - 180, 0, atol=1e-9)
    for viewmat, K in zip(viewmats, Ks):
        assert np.allclose(viewmat[:3, :3] @ viewmat[:3, :3].T, np.eye(3)) and np.linalg.det(viewmat[:3, :3]) > 0
        uv, depth = project_points(np.stack([center, center + [0, 0, 0.05]]), viewmat, K)
        assert np.allclose(uv[0], [48.0, 32.0]) and depth[0] == pytest.approx(radius)
        assert uv[1, 1] < uv[0, 1]   # world up is image up
    assert np.allclose(Ks[:, 0, 0], 48.0 / np.tan(np.radians(20.0)))


@pytest.mark.parametrize("fill", [0.3, 0.7, 1.0])
def test_distance_for_object_fills_the_stated_fraction(fill):
    half_extent, fov, width = np.array([0.03, 0.04, 0.12]), 40.0, 200
    distance = distance_for_object(half_extent, fov, fill)
    viewmats, Ks = orbit_cameras(np.zeros(3), distance, 1, 0.0, fov, width, width)
    radius = np.linalg.norm(half_extent)
    # the silhouette: points where the viewing ray is tangent to the bounding sphere
    eye = -viewmats[0, :3, :3].T @ viewmats[0, :3, 3]
    half_angle = np.arcsin(radius / distance)
    axis = -eye / distance
    side = np.cross(axis, [0.0, 0.0, 1.0])
    up = np.cross(side, axis)
    phi = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    rays = np.cos(half_angle) * axis + np.sin(half_angle) * (np.cos(phi)[:, None] * side + np.sin(phi)[:, None] * up)
    tangent = eye + np.sqrt(distance**2 - radius**2) * rays
    assert np.allclose(np.linalg.norm(tangent, axis=1), radius)
    uv, _ = project_points(tangent, viewmats[0], Ks[0])
    assert np.allclose(np.linalg.norm(uv - width / 2, axis=1), fill * width / 2)
    sphere = np.random.default_rng(0).normal(size=(2000, 3))
    sphere = radius * sphere / np.linalg.norm(sphere, axis=1, keepdims=True)
    uv, _ = project_points(sphere, viewmats[0], Ks[0])
    assert np.linalg.norm(uv - width / 2, axis=1).max() <= fill * width / 2 + 1e-9
