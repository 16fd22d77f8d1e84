"""Object model (tasks.control.object_model, its sources, tasks.control.geometry, tasks.control.gaussian_ply) and the
MPM particle fill (tasks.physics.particle_fill): known answers and clear errors.

Known answers: a sphere's area 4 pi R^2 and volume 4/3 pi R^3, its principal curvatures 1/R, outward normals;
the eight catalogue objects fit their configured bbox; a thin wall is one particle layer of mass area x
thickness; interior particles exist only with an interior and lie inside the wall; the 3DGS PLY round trip is
exact to float32; bad inputs give one-line errors naming the file and the fix.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
import trimesh
from omegaconf import OmegaConf

from conf.schema import ObjectConfig, SamplingConfig
from tasks.control.curvature import matrix_to_quaternion, shell_depth_volume
from tasks.control.gaussian_ply import C0, GaussianPlyError, read_gaussian_ply, write_gaussian_ply
from tasks.control.geometry import make_shape
from tasks.control.object_config import ObjectModelError
from tasks.control.object_model import build_object_model
from tasks.physics.particle_fill import build_mpm_particles

REPO = Path(__file__).resolve().parents[2]
EIGHT = ["can", "plush_toy", "rubber_duck", "clay", "tomato", "orange", "rubber_ball", "paper_cup"]
ARRAYS = {
    "surface_points": (("point", "xyz"), "m"),
    "surface_normals": (("point", "xyz"), "1"),
    "surface_curvature": (("point", "principal"), "1/m"),
    "surface_principal_dirs": (("point", "principal", "xyz"), "1"),
    "surface_area": (("point",), "m^2"),
    "gaussian_scales": (("point", "xyz"), "m"),
    "gaussian_rotations": (("point", "quat"), "1"),
    "gaussian_opacities": (("point",), "1"),
    "gaussian_colors": (("point", "rgb"), "1"),
    "particle_positions": (("particle", "xyz"), "m"),
    "particle_volumes": (("particle",), "m^3"),
    "particle_normals": (("particle", "xyz"), "1"),
    "wall_fibres": (("fibre", "layer"), "1"),
    "interior_positions": (("interior_particle", "xyz"), "m"),
    "interior_volumes": (("interior_particle",), "m^3"),
}
ATTRS = {"bbox_min", "bbox_max", "surface_area_total", "enclosed_volume", "wall_thickness", "particle_spacing",
         "thin_wall", "thin_wall_layers", "n_particles", "n_interior"}
# 3000 surface points, 4 mm particles, a wall thinner than the spacing in one layer on its mid-surface (the tests
# below check that sampling; the default two-layer split has its own test)
SAMPLING = OmegaConf.merge(OmegaConf.structured(SamplingConfig), {"thin_wall_layers": 1})


def build_with_particles(obj, sampling, grid_spacing=None):
    """The object model (surface Gaussians) and its MPM particles of the grid spacing ``grid_spacing`` (m; None: the
    particle spacing) as one (arrays, attrs), as the rollout sees them."""
    arrays, attrs = build_object_model(obj, sampling)
    p_arrays, p_attrs = build_mpm_particles(obj, sampling, grid_spacing)
    return {**arrays, **p_arrays}, {**attrs, **p_attrs}


def catalogue(name: str):
    return OmegaConf.merge(OmegaConf.structured(ObjectConfig), OmegaConf.load(REPO / "conf" / "object" / f"{name}.yaml"))


def make_obj(**kw):
    base = {"name": "probe", "display_name": "probe", "description": "a test object"}
    return OmegaConf.merge(OmegaConf.structured(ObjectConfig), {**base, **kw})


def quat_matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


@pytest.fixture(scope="module")
def built():
    """All eight catalogue objects, built once (with their build times)."""
    out = {}
    for name in EIGHT:
        t0 = time.perf_counter()
        arrays, attrs = build_with_particles(catalogue(name), SAMPLING)
        out[name] = (arrays, attrs, time.perf_counter() - t0)
    return out


# ----------------------------------------------------------------------------------------------- sphere
@pytest.mark.parametrize("kind", ["sphere", "ellipsoid"])  # analytic sphere / generic meshed implicit path
def test_sphere_known_answers(kind):
    R = 0.025
    arrays, attrs = build_with_particles(make_obj(geometry={"kind": kind, "size": [2 * R] * 3}, filled=True), SAMPLING)
    a = {k: v.data for k, v in arrays.items()}
    assert attrs["surface_area_total"] == pytest.approx(4 * np.pi * R ** 2, rel=0.02)
    assert attrs["enclosed_volume"] == pytest.approx(4 / 3 * np.pi * R ** 3, rel=0.03)
    assert a["surface_area"].sum() == pytest.approx(attrs["surface_area_total"], rel=1e-4)
    assert a["particle_volumes"].sum() == pytest.approx(4 / 3 * np.pi * R ** 3, rel=0.03)
    p, n = a["surface_points"].astype(float), a["surface_normals"].astype(float)
    assert len(p) == SAMPLING.surface_points
    assert np.abs(np.linalg.norm(p, axis=1) - R).max() < 1e-5  # on the surface
    assert np.all(np.sum(n * p, axis=1) > 0)  # outward
    assert np.abs(np.linalg.norm(n, axis=1) - 1).max() < 1e-5
    k = a["surface_curvature"]
    assert np.all(k[:, 0] >= k[:, 1])
    assert np.median(k, axis=0) == pytest.approx([1 / R, 1 / R], rel=0.10)
    # principal directions: unit, tangent, orthogonal; the rotation maps local (x, y, z) to (t1, t2, n)
    d = a["surface_principal_dirs"].astype(float)
    assert np.abs(np.einsum("nij,nj->ni", d, n)).max() < 1e-4
    assert np.abs(np.sum(d[:, 0] * d[:, 1], axis=1)).max() < 1e-4
    Rm = quat_matrix(a["gaussian_rotations"].astype(float))
    assert np.abs(Rm[:, :, 2] - n).max() < 1e-4 and np.abs(Rm[:, :, 0] - d[:, 0]).max() < 1e-4
    # blue-noise samples: no near-duplicates, spacing ~ sqrt(area per sample)
    from scipy.spatial import cKDTree

    nn = cKDTree(p).query(p, k=2)[0][:, 1]
    h = np.sqrt(4 * np.pi * R ** 2 / len(p))
    assert nn.min() > 0.3 * h and 0.7 * h < np.median(nn) < 1.3 * h
    s = a["gaussian_scales"]
    assert np.all(s[:, 2] < 0.2 * s[:, 0]) and np.median(s[:, 0]) == pytest.approx(0.6 * h, rel=0.2)


# ----------------------------------------------------------------------------------------------- catalogue
def test_all_eight_build_with_the_contract(built):
    for name, (arrays, attrs, _) in built.items():
        obj = catalogue(name)
        assert set(arrays) == set(ARRAYS), name
        for key, (dims, units) in ARRAYS.items():
            arr = arrays[key]
            assert tuple(arr.dims) == dims and arr.units == units, (name, key)
            assert arr.data.dtype == (np.int32 if key == "wall_fibres" else np.float32), (name, key)
            assert np.all(np.isfinite(arr.data)), (name, key)
        assert ATTRS <= set(attrs), name
        n = arrays["surface_points"].data.shape[0]
        assert n == SAMPLING.surface_points
        assert arrays["gaussian_colors"].data.min() >= 0 and arrays["gaussian_colors"].data.max() <= 1
        op = arrays["gaussian_opacities"].data
        assert np.all((op > 0) & (op < 1))
        q = arrays["gaussian_rotations"].data
        assert np.abs(np.linalg.norm(q, axis=1) - 1).max() < 1e-5
        assert attrs["n_particles"] == arrays["particle_positions"].data.shape[0] > 0
        assert attrs["n_interior"] == arrays["interior_positions"].data.shape[0]
        # the configured bbox, within one particle spacing, for the surface and the particles
        size, s = np.asarray(obj.geometry.size), SAMPLING.particle_spacing
        for key in ("surface_points", "particle_positions"):
            pts = arrays[key].data
            assert np.all(np.abs((pts.max(0) - pts.min(0)) - size) < s), (name, key)
            assert np.all(np.abs(0.5 * (pts.max(0) + pts.min(0))) < s), (name, key)
        assert np.allclose(attrs["bbox_max"], size / 2) and np.allclose(attrs["bbox_min"], -size / 2)
        # outward normals: the surface point + a small step along the normal leaves the solid
        shape = make_shape(obj.geometry.kind, size)
        p, nrm = arrays["surface_points"].data.astype(float), arrays["surface_normals"].data.astype(float)
        assert np.mean(shape.sdf(p + 5e-4 * nrm) > shape.sdf(p - 5e-4 * nrm)) > 0.99, name
        assert arrays["surface_area"].data.sum() == pytest.approx(attrs["surface_area_total"], rel=1e-4)
        assert attrs["thin_wall"] == (not obj.filled and obj.geometry.wall_thickness < s)


def test_eight_objects_are_fast(built):
    assert sum(t for *_, t in built.values()) < 15.0  # ~3 s on a laptop core; generous for shared CI


def test_a_wall_thinner_than_the_grid_is_sampled_in_gauss_layers_even_when_not_thinner_than_the_particles():
    """The orange's 4 mm peel at 4 mm particles: judged against the particle spacing alone it is a volume layer of
    the spacing (one particle through the thickness); judged against the 8 mm grid the solver holds it on (it is
    held in plane stress there) it is a thin wall, sampled in the two Gauss layers at +-t / (2 sqrt 3) of its
    mid-surface, half the wall's volume each, the wall volume the exact shell's as for every closed thin wall
    (known answers)."""
    obj = catalogue("orange")
    t, s = obj.geometry.wall_thickness, 0.004
    sampling = OmegaConf.merge(OmegaConf.structured(SamplingConfig), {"particle_spacing": s})
    _, by_spacing = build_with_particles(obj, sampling)
    arrays, by_grid = build_with_particles(obj, sampling, grid_spacing=2 * s)
    assert t == pytest.approx(s) and not by_spacing["thin_wall"] and by_spacing["thin_wall_layers"] == 0
    assert by_grid["thin_wall"] and by_grid["thin_wall_layers"] == 2
    shape = make_shape(obj.geometry.kind, obj.geometry.size)
    depth = -shape.sdf(arrays["particle_positions"].data.astype(float))  # below the outer surface, m (the wall's)
    gauss = t / (2 * np.sqrt(3))
    assert np.abs(np.minimum(np.abs(depth - (t / 2 - gauss)), np.abs(depth - (t / 2 + gauss)))).max() < 2e-4
    # the exact shell's, 4 pi (R^3 - (R - t)^3) / 3 = area x t x (1 - t / R + t^2 / (3 R^2)) = 0.897 area x t at
    # t / R = 0.107 (Steiner), as the volume layer's V(sdf < 0) - V(sdf < -t)
    R = obj.geometry.size[0] / 2
    shell = 4 / 3 * np.pi * (R ** 3 - (R - t) ** 3)
    assert by_grid["surface_area_total"] == pytest.approx(4 * np.pi * R ** 2, rel=1e-3)
    assert shell == pytest.approx(0.897 * by_grid["surface_area_total"] * t, rel=1e-3)
    assert by_grid["wall_volume"] == pytest.approx(shell, rel=0.01)
    assert by_spacing["wall_volume"] == pytest.approx(shell, rel=0.01)


def test_shell_depth_volume_is_steiners_formula():
    """Volume per outer area of a wall of thickness t (known answers): a sphere's shell, a cylinder's, a flat plate's,
    a saddle's (k1 = -k2: the terms cancel but the last), and a ball smaller than the wall (R = t / 2: the whole
    ball, R / 3 per area, not a negative volume past the centre)."""
    t, R, area = 0.004, 0.0375, np.full(5, 1e-6)
    k = np.array([[1 / R, 1 / R], [1 / R, 0.0], [0.0, 0.0], [1 / R, -1 / R], [2 / t, 2 / t]])
    got = shell_depth_volume(k, t, area)
    sphere = (R ** 3 - (R - t) ** 3) / (3 * R ** 2)
    cylinder = (R ** 2 - (R - t) ** 2) / (2 * R)
    assert got == pytest.approx([sphere, cylinder, t, t - t ** 3 / (3 * R ** 2), t / 6], rel=1e-9)
    # the representation resolves no curvature above 2 / sqrt(area): a finer crease counts as that one
    assert shell_depth_volume(np.array([[1e6, 0.0]]), t, np.array([1e-4]))[0] == pytest.approx(
        shell_depth_volume(np.array([[200.0, 0.0]]), t, np.array([1e-4]))[0])


def test_thin_wall_can_is_one_layer_with_physical_mass(built):
    arrays, attrs, _ = built["can"]
    obj = catalogue("can")
    t, s = obj.geometry.wall_thickness, SAMPLING.particle_spacing
    assert t == pytest.approx(1e-4) and attrs["thin_wall"] is True
    shape = make_shape("can", obj.geometry.size)
    pos = arrays["particle_positions"].data.astype(float)
    # one layer on the wall's mid-surface t/2 inside the outer surface
    assert np.abs(shape.sdf(pos) + t / 2).max() < 2e-5
    # total wall volume = area x real thickness (aluminium mass = rho A t) less Steiner's curvature term, t / (2 R) =
    # 0.15 % on the side, more on the rims' bends
    area = attrs["surface_area_total"]
    assert attrs["wall_volume"] == pytest.approx(arrays["particle_volumes"].data.sum(), rel=1e-6)
    assert 0.995 * area * t < attrs["wall_volume"] < 0.9985 * area * t
    # about one particle per s^2 of wall, spaced ~ s
    assert attrs["n_particles"] == pytest.approx(area / s ** 2, rel=0.15)
    from scipy.spatial import cKDTree

    nn = cKDTree(pos).query(pos, k=2)[0][:, 1]
    assert nn.min() > 0.6 * s and 0.7 * s < np.median(nn) < 1.2 * s
    n = arrays["particle_normals"].data.astype(float)
    assert np.mean(shape.sdf(pos + 5e-4 * n) > shape.sdf(pos - 5e-4 * n)) > 0.99


def test_interior_only_when_set_and_inside_the_wall(built):
    for name, (arrays, attrs, _) in built.items():
        obj = catalogue(name)
        ipos = arrays["interior_positions"].data.astype(float)
        if obj.interior is None:
            assert ipos.shape == (0, 3) and arrays["interior_volumes"].data.shape == (0,), name
            continue
        assert len(ipos) > 0, name
        shape = make_shape(obj.geometry.kind, obj.geometry.size)
        t = obj.geometry.wall_thickness
        assert shape.sdf(ipos).max() < -t, name  # inside the wall's inner surface
        wall, cavity = arrays["particle_volumes"].data.sum(), arrays["interior_volumes"].data.sum()
        assert wall + cavity == pytest.approx(attrs["enclosed_volume"], rel=0.02), name


def test_thick_wall_and_solid_particles(built):
    arrays, attrs, _ = built["orange"]  # 4 mm peel = spacing: grid points inside the wall
    obj = catalogue("orange")
    t = obj.geometry.wall_thickness
    assert attrs["thin_wall"] is False and attrs["thin_wall_layers"] == 0
    shape = make_shape("sphere", obj.geometry.size)
    d = shape.sdf(arrays["particle_positions"].data.astype(float))
    assert d.max() < 0 and d.min() > -t
    R = obj.geometry.size[0] / 2
    assert attrs["wall_volume"] == pytest.approx(4 / 3 * np.pi * (R ** 3 - (R - t) ** 3), rel=0.03)
    arrays, attrs, _ = built["clay"]  # solid block
    assert attrs["wall_volume"] == pytest.approx(attrs["enclosed_volume"], rel=1e-6)
    assert attrs["enclosed_volume"] == pytest.approx(0.06 * 0.05 * 0.04, rel=0.05)  # rounded edges


def test_paper_cup_is_an_open_sheet(built):
    arrays, attrs, _ = built["paper_cup"]
    shape = make_shape("cup", catalogue("paper_cup").geometry.size)
    assert attrs["thin_wall"] is True
    assert shape.open_distance(arrays["particle_positions"].data.astype(float)).max() < 1e-6
    p = arrays["surface_points"].data
    r = np.hypot(p[:, 0], p[:, 1])
    top = p[:, 2] > 0.045 - 1e-4
    assert not np.any(top & (r < 0.9 * 0.04))  # open top: no lid
    assert np.sum(p[:, 2] < -0.045 + 1e-6) > 50  # closed bottom


def test_colours_are_recognisable(built):
    def col(name):
        a = built[name][0]
        return a["surface_points"].data, a["gaussian_colors"].data

    p, c = col("can")
    top = p[:, 2] > 0.055
    assert np.allclose(c[top].mean(0), c[top].mean(), atol=0.05) and c[top].mean() > 0.5  # silver lid/rim
    red = (c[:, 0] > 0.5) & (c[:, 1] < 0.1)
    white = c.min(axis=1) > 0.8
    assert red.mean() > 0.4 and 0.05 < white.mean() < 0.4
    p, c = col("tomato")
    green = c[:, 1] > c[:, 0]
    assert green[p[:, 2] > 0.027].mean() > 0.5  # calyx around the top pole (half height 0.0275)
    assert green[p[:, 2] > 0.025].sum() > 20 and not green[p[:, 2] < 0.02].any()
    assert np.mean(c[p[:, 2] < 0.02, 0] > 3 * c[p[:, 2] < 0.02, 1]) > 0.99  # red elsewhere
    p, c = col("rubber_duck")
    bill = p[:, 0] > 0.04
    assert np.mean(c[bill, 1] < 0.4) > 0.5  # orange bill
    assert np.mean((c[:, 0] > 0.7) & (c[:, 1] > 0.5)) > 0.7  # yellow body
    p, c = col("rubber_ball")
    assert np.mean(c[:, 2] > 0.5) == pytest.approx(0.5, abs=0.1)  # stripes: half blue
    p, c = col("paper_cup")
    assert 0.2 < np.mean(c[:, 2] > 0.3 * c.sum(1) + 0.1) < 0.8  # white with a coloured band


def test_deterministic_from_seed():
    obj = catalogue("rubber_duck")
    a1, _ = build_with_particles(obj, SAMPLING)
    a2, _ = build_with_particles(obj, SAMPLING)
    a3, _ = build_with_particles(obj, OmegaConf.merge(SAMPLING, {"seed": 1}))
    for k in ARRAYS:
        assert np.array_equal(a1[k].data, a2[k].data), k
    assert not np.array_equal(a1["surface_points"].data, a3["surface_points"].data)


def test_particles_come_from_the_content_and_seed_not_the_name(tmp_path):
    """Issue 15: the same object under two names (and labels) gets bitwise identical Gaussians and particles; the
    same mesh file under two paths too; another ``sampling.seed`` draws different ones."""
    small = OmegaConf.merge(SAMPLING, {"surface_points": 400, "particle_spacing": 0.006})
    ball = catalogue("rubber_ball")
    a, _ = build_with_particles(ball, small)
    b, _ = build_with_particles(OmegaConf.merge(ball, {"name": "sphere_b", "display_name": "Another ball"}), small)
    for k in ARRAYS:
        assert a[k].data.tobytes() == b[k].data.tobytes(), k
    c, _ = build_with_particles(ball, OmegaConf.merge(small, {"seed": 1}))
    assert not np.array_equal(a["particle_positions"].data, c["particle_positions"].data)
    assert not np.array_equal(a["surface_points"].data, c["surface_points"].data)
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.03)
    (tmp_path / "one").mkdir()
    (tmp_path / "two").mkdir()
    mesh.export(tmp_path / "one" / "ball.stl")
    mesh.export(tmp_path / "two" / "other.stl")
    built_mesh = [build_with_particles(make_obj(name=name, geometry={"kind": "mesh", "path": str(path),
                                                                   "size": [0.06] * 3}, filled=True), small)[0]
                  for name, path in (("m1", tmp_path / "one" / "ball.stl"), ("m2", tmp_path / "two" / "other.stl"))]
    for k in ARRAYS:
        assert built_mesh[0][k].data.tobytes() == built_mesh[1][k].data.tobytes(), k


def test_thin_wall_in_two_layers_at_the_thickness_gauss_points(built):
    """``sampling.thin_wall_layers: 2``: the ball's one layer (3 mm wall, 4 mm spacing) split into two at
    +-t / (2 sqrt 3) along the normal, each particle with half the volume; the wall's volume and everything else
    the same."""
    one, attrs1, _ = built["rubber_ball"]
    two, attrs2 = build_with_particles(catalogue("rubber_ball"), OmegaConf.merge(SAMPLING, {"thin_wall_layers": 2}))
    t = catalogue("rubber_ball").geometry.wall_thickness
    p1, n1 = one["particle_positions"].data.astype(float), one["particle_normals"].data.astype(float)
    p2, n2 = two["particle_positions"].data.astype(float), two["particle_normals"].data.astype(float)
    m = len(p1)
    assert attrs2["n_particles"] == 2 * m and attrs2["thin_wall"] is True
    assert attrs1["thin_wall_layers"] == 1 and attrs2["thin_wall_layers"] == 2
    off = t / (2 * np.sqrt(3))
    np.testing.assert_allclose(p2[:m], p1 + off * n1, atol=1e-6)
    np.testing.assert_allclose(p2[m:], p1 - off * n1, atol=1e-6)
    np.testing.assert_array_equal(n2, np.concatenate([n1, n1]))
    # each normal fibre joins an outer particle to its inner twin, t / sqrt 3 apart along the wall's normal, once
    fib = two["wall_fibres"].data
    assert one["wall_fibres"].data.shape == (0, 2) and fib.shape == (m, 2) and fib.dtype == np.int32
    assert np.array_equal(np.sort(fib.ravel()), np.arange(2 * m))
    np.testing.assert_allclose(p2[fib[:, 0]] - p2[fib[:, 1]], 2 * off * n1, atol=1e-6)
    v1, v2 = one["particle_volumes"].data.astype(float), two["particle_volumes"].data.astype(float)
    np.testing.assert_allclose(v2, np.concatenate([v1, v1]) / 2, rtol=1e-6)
    assert v2.sum() == pytest.approx(v1.sum(), rel=1e-6) and attrs2["wall_volume"] == attrs1["wall_volume"]
    np.testing.assert_array_equal(two["surface_points"].data, one["surface_points"].data)
    # two-point Gauss rule: a strain linear through the thickness, e(z) = kappa z, integrates exactly
    z = np.array([off, -off])
    assert np.sum(0.5 * t * z ** 2) == pytest.approx(t ** 3 / 12)
    with pytest.raises(ObjectModelError, match="sampling.thin_wall_layers must be 1, 2 or 3, got 4"):
        build_with_particles(catalogue("rubber_ball"), OmegaConf.merge(SAMPLING, {"thin_wall_layers": 4}))


def test_thin_wall_in_three_layers_integrates_a_quadratic_strain_through_the_wall(built):
    """``sampling.thin_wall_layers: 3``: the ball's one layer split into three, at +-sqrt(3/5) t / 2 along the normal
    with 5/18 of the volume each and on the mid-surface with 8/18 (three-point Gauss-Legendre); each fibre joins
    outer, inner and middle once; the wall's volume the same.  The rule integrates z^2 and z^4 exactly (a strain
    linear and quadratic through the wall: its bending and the grid's quadratic part), two points only z^2."""
    one, attrs1, _ = built["rubber_ball"]
    three, attrs3 = build_with_particles(catalogue("rubber_ball"), OmegaConf.merge(SAMPLING, {"thin_wall_layers": 3}))
    t = catalogue("rubber_ball").geometry.wall_thickness
    p1, n1 = one["particle_positions"].data.astype(float), one["particle_normals"].data.astype(float)
    p3 = three["particle_positions"].data.astype(float)
    m = len(p1)
    assert attrs3["n_particles"] == 3 * m and attrs3["thin_wall_layers"] == 3
    off = 0.5 * np.sqrt(0.6) * t
    np.testing.assert_allclose(p3, np.concatenate([p1 + off * n1, p1 - off * n1, p1]), atol=1e-6)
    fib = three["wall_fibres"].data
    assert fib.shape == (m, 3) and np.array_equal(np.sort(fib.ravel()), np.arange(3 * m))
    np.testing.assert_allclose(p3[fib[:, 0]] - p3[fib[:, 1]], 2 * off * n1, atol=1e-6)
    np.testing.assert_allclose(p3[fib[:, 2]], 0.5 * (p3[fib[:, 0]] + p3[fib[:, 1]]), atol=1e-6)
    v1, v3 = one["particle_volumes"].data.astype(float), three["particle_volumes"].data.astype(float)
    np.testing.assert_allclose(v3, np.concatenate([5 * v1, 5 * v1, 8 * v1]) / 18, rtol=1e-6)
    assert attrs3["wall_volume"] == pytest.approx(attrs1["wall_volume"], rel=1e-6)
    z, w = np.array([off, -off, 0.0]), t * np.array([5, 5, 8]) / 18
    assert np.sum(w * z ** 2) == pytest.approx(t ** 3 / 12) and np.sum(w * z ** 4) == pytest.approx(t ** 5 / 80)
    z2 = np.array([1, -1]) * t / (2 * np.sqrt(3))
    assert np.sum(0.5 * t * z2 ** 4) == pytest.approx(t ** 5 / 144)  # two points: 5/9 of the quartic moment


def test_config_errors_are_one_line():
    cases = [
        (make_obj(geometry={"kind": "sphere", "wall_thickness": 0.0}, filled=False), "wall_thickness is 0"),
        (make_obj(geometry={"kind": "block"}, filled=True, interior="juice"), "filled is true"),
        (make_obj(geometry={"kind": "banana"}, filled=True), "geometry.kind 'banana' is unknown"),
        (make_obj(geometry={"kind": "mesh"}, filled=True), "geometry.path is required"),
    ]
    for obj, text in cases:
        with pytest.raises(ObjectModelError, match=text) as exc:
            build_with_particles(obj, SAMPLING)
        assert "\n" not in str(exc.value)


# ----------------------------------------------------------------------------------------------- 3DGS PLY
def random_gaussians(n=257, seed=0):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    return dict(
        means=rng.normal(size=(n, 3)).astype(np.float32) * 0.05,
        scales=np.exp(rng.uniform(-9, -4, size=(n, 3))).astype(np.float32),
        rotations=(q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32),
        opacities=rng.uniform(0.01, 0.99, size=n).astype(np.float32),
        colors=rng.uniform(0, 1, size=(n, 3)).astype(np.float32),
    )


def test_ply_round_trip_exact_to_float32(tmp_path):
    g = random_gaussians()
    path = write_gaussian_ply(tmp_path / "g.ply", **g)
    header = path.read_bytes().split(b"end_header\n")[0].decode()
    assert "format binary_little_endian 1.0" in header and "element vertex 257" in header
    names = [ln.split()[-1] for ln in header.splitlines() if ln.startswith("property")]
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert names[9:54] == [f"f_rest_{i}" for i in range(45)]
    assert names[54:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert all(f"property float {nm}" in header for nm in names)
    back = read_gaussian_ply(path)
    assert np.array_equal(back["means"], g["means"])  # stored as is: bit exact
    for key in ("scales", "rotations", "opacities"):
        assert back[key].dtype == np.float32
        np.testing.assert_allclose(back[key], g[key], rtol=2e-6, atol=2e-7, err_msg=key)
    np.testing.assert_allclose(back["colors"], g["colors"], atol=2e-6)  # through sRGB and back, float32 f_dc
    assert back["sh_rest"].shape == (257, 15, 3) and not back["sh_rest"].any()
    # stored values are the raw parameters of the Inria layout
    dtype = np.dtype([(nm, "<f4") for nm in names])
    raw = np.frombuffer(path.read_bytes()[len(header) + len("end_header\n"):], dtype=dtype)
    # f_dc holds the display (sRGB) colour, as 3DGS viewers read it; the reader returns linear RGB
    srgb = np.where(g["colors"][:, 0] <= 0.0031308, 12.92 * g["colors"][:, 0],
                    1.055 * g["colors"][:, 0].astype(np.float64) ** (1 / 2.4) - 0.055)
    np.testing.assert_allclose(raw["f_dc_0"], (srgb - 0.5) / C0, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(raw["scale_1"], np.log(g["scales"][:, 1]), rtol=1e-6)
    np.testing.assert_allclose(1 / (1 + np.exp(-raw["opacity"])), g["opacities"], rtol=1e-6)


def test_ply_reader_accepts_ascii_and_extra_elements(tmp_path):
    props = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
             "rot_0", "rot_1", "rot_2", "rot_3"]
    rows = ["0.1 0.2 0.3 0 0 0 0 -5 -5 -5 1 0 0 0", "1 2 3 1 1 1 2 -4 -4 -4 0 0 0 2"]
    text = "\n".join(["ply", "format ascii 1.0", "comment test", "element vertex 2"]
                     + [f"property float {p}" for p in props]
                     + ["element face 0", "property list uchar int vertex_indices", "end_header"] + rows) + "\n"
    (tmp_path / "a.ply").write_text(text)
    g = read_gaussian_ply(tmp_path / "a.ply")
    np.testing.assert_allclose(g["means"], [[0.1, 0.2, 0.3], [1, 2, 3]], rtol=1e-6)
    np.testing.assert_allclose(g["opacities"], [0.5, 1 / (1 + np.exp(-2))], rtol=1e-6)
    np.testing.assert_allclose(g["rotations"][1], [0, 0, 0, 1])
    np.testing.assert_allclose(g["display_colors"][1], 0.5 + C0, rtol=1e-6)  # the file's display colour
    np.testing.assert_allclose(g["colors"][1], ((0.5 + C0 + 0.055) / 1.055) ** 2.4, rtol=1e-6)  # read as linear


def test_malformed_ply_errors_name_file_and_fix(tmp_path):
    g = random_gaussians(10)
    good = write_gaussian_ply(tmp_path / "good.ply", **g).read_bytes()
    (tmp_path / "trunc.ply").write_bytes(good[:-100])
    (tmp_path / "notply.ply").write_bytes(b"hello world\n")
    (tmp_path / "nohdr.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\n")
    mesh_ply = tmp_path / "mesh.ply"
    trimesh.creation.box().export(mesh_ply)
    cases = [
        ("missing.ply", "does not exist"),
        ("trunc.ply", r"is truncated: header declares 10 vertices"),
        ("notply.ply", "is not a PLY file"),
        ("nohdr.ply", "no 'end_header'"),
        ("mesh.ply", r"is a triangle mesh \(12 faces, no Gaussian properties such as f_dc_0\), not a 3DGS splat: "
                     r"give it as a mesh with geometry.kind=mesh"),
    ]
    for fname, text in cases:
        with pytest.raises(GaussianPlyError, match=text) as exc:
            read_gaussian_ply(tmp_path / fname)
        msg = str(exc.value)
        assert fname in msg and "\n" not in msg
    # through the object model the same message surfaces as an ObjectModelError
    for fname, text in cases:
        with pytest.raises(ObjectModelError, match=text):
            build_with_particles(make_obj(geometry={"kind": "ply", "path": str(tmp_path / fname)}, filled=True), SAMPLING)


def test_ply_object_from_a_written_splat(tmp_path, built):
    arrays, attrs, _ = built["orange"]
    a = {k: v.data for k, v in arrays.items()}
    path = write_gaussian_ply(tmp_path / "orange.ply", a["surface_points"], a["gaussian_scales"],
                              a["gaussian_rotations"], a["gaussian_opacities"], a["gaussian_colors"])
    obj = OmegaConf.merge(catalogue("orange"), {"geometry": {"kind": "ply", "path": str(path)}})
    b_arrays, b = build_with_particles(obj, SAMPLING)
    bb = {k: v.data for k, v in b_arrays.items()}
    # the same Gaussians, fitted into the configured bbox (uniform scale ~1: the samples' own bbox is a hair smaller)
    np.testing.assert_allclose(bb["surface_points"], a["surface_points"], atol=2e-4)
    assert np.allclose(np.subtract(b["bbox_max"], b["bbox_min"]).max(), 0.075)
    np.testing.assert_allclose(bb["gaussian_colors"], a["gaussian_colors"], atol=1e-5)
    assert np.mean(np.sum(bb["surface_normals"] * a["surface_normals"], axis=1) > 0.95) > 0.98
    assert b["surface_area_total"] == pytest.approx(attrs["surface_area_total"], rel=0.03)
    assert b["enclosed_volume"] == pytest.approx(attrs["enclosed_volume"], rel=0.03)
    assert np.median(bb["surface_curvature"], axis=0) == pytest.approx([1 / 0.0375] * 2, rel=0.1)
    assert b["n_interior"] > 0 and b["wall_volume"] == pytest.approx(attrs["wall_volume"], rel=0.1)


# ----------------------------------------------------------------------------------------------- meshes
@pytest.mark.parametrize("ext", ["obj", "stl", "glb"])
def test_mesh_icosphere_loads(tmp_path, ext):
    R = 0.03
    path = tmp_path / f"ball.{ext}"
    trimesh.creation.icosphere(subdivisions=4, radius=R).export(path)
    obj = make_obj(geometry={"kind": "mesh", "path": str(path), "size": [2 * R] * 3, "wall_thickness": 0.002},
                   interior="juice")
    arrays, attrs = build_with_particles(obj, SAMPLING)
    a = {k: v.data for k, v in arrays.items()}
    assert attrs["enclosed_volume"] == pytest.approx(4 / 3 * np.pi * R ** 3, rel=0.03)
    assert attrs["surface_area_total"] == pytest.approx(4 * np.pi * R ** 2, rel=0.02)
    assert np.all(np.sum(a["surface_normals"] * a["surface_points"], axis=1) > 0)
    assert np.median(a["surface_curvature"], axis=0) == pytest.approx([1 / R, 1 / R], rel=0.15)
    assert attrs["thin_wall"]  # the exact shell's volume (Steiner's formula), 6.5 % below area x t at t / R = 0.067
    assert a["particle_volumes"].sum() == pytest.approx(4 / 3 * np.pi * (R ** 3 - (R - 0.002) ** 3), rel=0.02)
    assert np.linalg.norm(a["interior_positions"], axis=1).max() < R - 0.002
    # a solid fill from trimesh's voxelisation (no rtree / embree needed)
    arrays, attrs = build_with_particles(make_obj(geometry={"kind": "mesh", "path": str(path), "size": [2 * R] * 3},
                                                filled=True), SAMPLING)
    assert arrays["particle_volumes"].data.sum() == pytest.approx(4 / 3 * np.pi * R ** 3, rel=0.03)
    assert attrs["n_particles"] == pytest.approx(4 / 3 * np.pi * R ** 3 / SAMPLING.particle_spacing ** 3, rel=0.1)


def test_mesh_errors_name_file_and_fix(tmp_path):
    box = trimesh.creation.box(extents=[0.05, 0.04, 0.03])
    holey = box.copy()
    holey.update_faces(np.arange(len(box.faces)) != 0)  # drop one triangle: three open edges
    holey.export(tmp_path / "holey.obj")
    (tmp_path / "empty.obj").write_text("# no geometry\n")
    cases = [
        ("nothere.obj", "does not exist: set object.geometry.path"),
        ("holey.obj", r"is not watertight \(3 open edges\): repair it, e.g. trimesh.repair.fill_holes"),
        ("empty.obj", r"is empty \(0 faces\)"),
    ]
    for fname, text in cases:
        with pytest.raises(ObjectModelError, match=text) as exc:
            build_with_particles(make_obj(geometry={"kind": "mesh", "path": str(tmp_path / fname)}, filled=True), SAMPLING)
        assert fname in str(exc.value) and "\n" not in str(exc.value)
    # the closed box works, scaled uniformly into the configured bbox
    box.export(tmp_path / "box.stl")
    arrays, attrs = build_with_particles(
        make_obj(geometry={"kind": "mesh", "path": str(tmp_path / "box.stl"), "size": [0.1, 0.1, 0.1]}, filled=True),
        SAMPLING)
    assert np.allclose(np.subtract(attrs["bbox_max"], attrs["bbox_min"]), [0.1, 0.08, 0.06])
    assert attrs["enclosed_volume"] == pytest.approx(0.1 * 0.08 * 0.06, rel=1e-6)


def test_matrix_to_quaternion_round_trip():
    rng = np.random.default_rng(3)
    q = rng.normal(size=(500, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.where(q[:, :1] < 0, -1, 1)
    np.testing.assert_allclose(matrix_to_quaternion(quat_matrix(q)), q, atol=1e-9)


def _two_overlapping_boxes() -> trimesh.Trimesh:
    """Two closed boxes, the second poking through the first: every edge is shared (watertight), yet faces
    pass through each other (a body and a head modelled as two shells)."""
    a = trimesh.creation.box(extents=[0.05, 0.04, 0.03])
    b = trimesh.creation.box(extents=[0.03, 0.05, 0.02])
    b.apply_translation([0.02, 0.01, 0.005])
    return trimesh.util.concatenate([a, b])


def _folded_sphere() -> trimesh.Trimesh:
    """One closed sphere with a vertex pulled through the body to the far side: its fan of faces crosses the
    opposite wall."""
    ico = trimesh.creation.icosphere(subdivisions=3, radius=0.03)
    v = ico.vertices.copy()
    v[0] *= -1.5
    return trimesh.Trimesh(v, ico.faces, process=False)


def test_crossing_triangle_pairs_finds_real_self_intersections():
    from tasks.control.geometry import crossing_triangle_pairs

    overlapping, folded = _two_overlapping_boxes(), _folded_sphere()
    assert overlapping.is_watertight and folded.is_watertight
    pairs = crossing_triangle_pairs(overlapping.vertices, overlapping.faces)
    assert len(pairs) > 0 and np.all(pairs[:, 0] < 12) and np.all(pairs[:, 1] >= 12)  # box A's faces x box B's
    pairs = crossing_triangle_pairs(folded.vertices, folded.faces)
    moved = np.flatnonzero((folded.faces == 0).any(axis=1))  # the fan around the pulled vertex
    assert len(pairs) > 0 and np.all(np.isin(pairs, moved).any(axis=1))
    # independent check with trimesh: each reported pair really crosses (a segment of one pierces the other)
    for i, j in pairs:
        a, b = folded.triangles[i], folded.triangles[j]
        starts, ends = np.concatenate([a, b]), np.concatenate([np.roll(a, -1, 0), np.roll(b, -1, 0)])
        other = [b] * 3 + [a] * 3
        hits = [trimesh.triangles.points_to_barycentric(np.array([tri]), np.array([p]))[0]
                for tri, p in zip(other, _segment_plane_points(starts, ends, other)) if p is not None]
        assert any(np.all(w > 0) for w in hits)
    # closed surfaces that touch nothing: no false positives (sphere, torus, two disjoint boxes, a box of 12)
    apart = _two_overlapping_boxes().split(only_watertight=False)
    apart[1].apply_translation([0.2, 0, 0])
    for mesh in (trimesh.creation.icosphere(subdivisions=5), trimesh.creation.torus(0.03, 0.01),
                 trimesh.util.concatenate(list(apart)), trimesh.creation.box()):
        assert len(crossing_triangle_pairs(mesh.vertices, mesh.faces)) == 0


def _segment_plane_points(starts, ends, tris):
    """Where each segment meets the plane of its triangle (None when it does not, within the segment)."""
    out = []
    for s, e, tri in zip(starts, ends, tris):
        n = np.cross(tri[1] - tri[0], tri[2] - tri[0])
        denom = n @ (e - s)
        t = None if abs(denom) < 1e-15 else (n @ (tri[0] - s)) / denom
        out.append(None if t is None or not 0 < t < 1 else s + t * (e - s))
    return out


def test_self_intersecting_mesh_is_refused_with_the_file_and_the_fix(tmp_path):
    for name, mesh in (("overlap.obj", _two_overlapping_boxes()), ("folded.stl", _folded_sphere())):
        mesh.export(tmp_path / name)
        with pytest.raises(ObjectModelError) as exc:
            build_with_particles(make_obj(geometry={"kind": "mesh", "path": str(tmp_path / name)}, filled=True),
                               SAMPLING)
        msg = str(exc.value)
        assert msg.startswith(f"mesh {tmp_path / name} intersects itself (") and "boolean union" in msg
        assert "\n" not in msg


def test_a_user_file_keeps_its_size_or_states_the_rescale(tmp_path):
    """A mesh or splat is fitted into geometry.size: at the size given nothing is said, a rescale is one line with
    the factor, and a file of 1 km or 1 um is refused with the fix."""
    from tasks.control.sources.base import fit_statement
    from tasks.control.sources.by_kind import geometry_file_bounds

    def check_geometry_file(kind: str, path: str, size: list[float]) -> str | None:  # the preflight's two calls
        lo, hi, what = geometry_file_bounds(kind, path)
        return fit_statement(what, lo, hi, size)

    box = trimesh.creation.box(extents=[0.05, 0.04, 0.03])
    box.export(tmp_path / "box.stl")
    assert check_geometry_file("mesh", str(tmp_path / "box.stl"), [0.05, 0.04, 0.03]) is None
    assert check_geometry_file("mesh", str(tmp_path / "box.stl"), [0.1, 0.1, 0.1]) == (
        f"mesh {tmp_path / 'box.stl'} spans 0.05 x 0.04 x 0.03 (file units): scaled by 2 to fit geometry.size "
        f"[0.1, 0.1, 0.1] m")
    g = random_gaussians()
    g["means"] = g["means"] * np.float32(1e5)  # a splat of ~30 km
    path = write_gaussian_ply(tmp_path / "km.ply", **g)
    with pytest.raises(ObjectModelError) as exc:
        check_geometry_file("ply", str(path), [0.05, 0.05, 0.05])
    msg = str(exc.value)
    assert msg.startswith(f"PLY {path} spans ") and " (file units) and would be scaled by " in msg
    assert msg.endswith("to fit geometry.size [0.05, 0.05, 0.05] m: export it in metres or millimetres, or set "
                        "geometry.size to the object's real size")
