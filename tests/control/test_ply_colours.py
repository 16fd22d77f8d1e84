"""True colours through 3DGS PLY files: 0.5 + C0 f_dc is the display (sRGB) colour, as 3DGS viewers read it; the 4D
sequence is written in the reference layout (SH degree 3, f_rest_* zeros, normals present)."""
from __future__ import annotations

import numpy as np
import torch

from tasks.control.gaussian_ply import C0, REFERENCE_PROPERTIES, read_gaussian_ply, write_gaussian_ply
from tasks.generation.ply_sequence import write_ply_sequence
from tasks.render.cameras import orbit_cameras
from tasks.render.colour import to_srgb_uint8
from tasks.render.splat import rasterization

DISPLAY = np.array([224, 51, 35]) / 255.0  # the tomato's colour in our render, sRGB


def _header(path) -> list[str]:
    raw = path.read_bytes()
    head = raw[:raw.index(b"end_header")].decode("ascii").splitlines()
    return [line.split()[-1] for line in head if line.startswith("property")]


def test_a_known_colour_round_trips_write_read_render_within_one_level(tmp_path):
    """Linear colour -> PLY -> read -> our renderer -> 8-bit sRGB lands within 1/255 of the display colour, and the
    file stores f_dc = (display - 0.5) / C0, what every 3DGS viewer shows."""
    linear = np.where(DISPLAY <= 0.04045, DISPLAY / 12.92, ((DISPLAY + 0.055) / 1.055) ** 2.4)
    n = 200
    rng = np.random.default_rng(0)
    means = rng.normal(0, 0.01, (n, 3))
    path = write_gaussian_ply(tmp_path / "g.ply", means, np.full((n, 3), 0.01), np.tile([1.0, 0, 0, 0], (n, 1)),
                              np.full(n, 0.99), np.tile(linear, (n, 1)))
    raw = np.frombuffer(path.read_bytes()[path.read_bytes().index(b"end_header\n") + 11:],
                        dtype=np.dtype([(p, "<f4") for p in _header(path)]))
    np.testing.assert_allclose(0.5 + C0 * np.stack([raw[f"f_dc_{i}"] for i in range(3)], -1), np.broadcast_to(DISPLAY, (n, 3)),
                               atol=1e-5)  # float32 storage; a level is 3.9e-3
    g = read_gaussian_ply(path)
    np.testing.assert_allclose(g["colors"], np.broadcast_to(linear, (n, 3)), atol=1e-5)
    np.testing.assert_allclose(g["display_colors"], np.broadcast_to(DISPLAY, (n, 3)), atol=1e-5)
    viewmats, Ks = orbit_cameras(np.zeros(3), 0.3, 1, 0.0, 40.0, 32, 32)
    colors, _, _ = rasterization(torch.as_tensor(g["means"]), torch.as_tensor(g["rotations"]),
                                 torch.as_tensor(g["scales"]), torch.as_tensor(g["opacities"]),
                                 torch.as_tensor(g["colors"]), torch.as_tensor(viewmats, dtype=torch.float32),
                                 torch.as_tensor(Ks, dtype=torch.float32), 32, 32, render_mode="RGB")
    centre = to_srgb_uint8(colors[0, 16, 16].numpy().astype(np.float32))
    assert np.abs(centre.astype(int) - np.rint(DISPLAY * 255).astype(int)).max() <= 1


def test_the_4d_sequence_has_the_reference_3dgs_layout_property_by_property(tmp_path):
    [path] = write_ply_sequence(tmp_path, np.zeros((1, 2, 3)), np.tile([1e-6, 0, 0, 1e-6, 0, 1e-6], (1, 2, 1)),
                                np.full((2, 3), 0.4), np.full(2, 0.9), np.zeros((1, 1, 3)), np.ones((1, 1), bool),
                                np.full((1, 3), 0.7), np.full(1, 0.5), np.full((1, 3), 0.002), np.array([0]))
    assert _header(path) == list(REFERENCE_PROPERTIES)
    assert len([p for p in REFERENCE_PROPERTIES if p.startswith("f_rest_")]) == 45
    assert all(line.startswith("property float ") for line in path.read_bytes()[:path.read_bytes().index(
        b"end_header")].decode().splitlines() if line.startswith("property"))
    g = read_gaussian_ply(path)
    assert g["sh_rest"].shape == (3, 15, 3) and not g["sh_rest"].any()
