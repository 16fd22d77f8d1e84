"""The hand drawn from the recorded signals: exact capsule depth and silhouette, depth compositing with the object,
fingers that end at the recorded fingertips with their bone lengths kept."""
from __future__ import annotations

import numpy as np

from tasks.render.cameras import look_at
from tasks.render.hand import (
    Capsules,
    HandLayer,
    composite_hand,
    draw_hand,
    finger_chain,
    hand_sequence,
    render_hand,
    shade_skin,
)

W = H = 64
FOCAL = 64.0
K = np.array([[FOCAL, 0.0, W / 2], [0.0, FOCAL, H / 2], [0.0, 0.0, 1.0]])
CAMERA = look_at(np.array([0.0, -0.5, 0.0]), np.zeros(3))  # at y = -0.5 m looking along +y, z up


def test_a_capsule_across_the_view_has_its_front_at_z_minus_r_and_a_one_pixel_silhouette():
    r = 0.02
    layer = render_hand(Capsules(np.array([[-0.1, 0.0, 0.0]]), np.array([[0.1, 0.0, 0.0]]), np.array([r])), CAMERA,
                        K, W, H, np.array([0.7, 0.5, 0.4]))
    # the pixel rows straddling the axis, their centres half a pixel (0.5 / f x 0.5 m) off it: the ray hits the
    # cylinder's front at depth 0.5 - sqrt(r^2 - offset^2) (to the ray's slant, ~1e-5 m)
    centre = layer.depth[H // 2 - 1:H // 2 + 1, W // 2]
    offset = 0.5 / FOCAL * 0.5
    assert np.allclose(centre, 0.5 - np.sqrt(r * r - offset * offset), atol=3e-5)
    # the silhouette: half-height r f / (z - r)... within a pixel; coverage 1 inside, 0 two pixels outside
    half_px = FOCAL * r / 0.5
    column = layer.coverage[:, W // 2]
    assert column[H // 2] == 1.0 and column[int(H / 2 + half_px + 2)] == 0.0 and column[int(H / 2 - half_px - 3)] == 0.0
    assert abs(column.sum() - 2 * half_px) < 1.0  # the anti-aliased area is the true height to within a pixel
    # shading lit by the light from the upper left: the upper half brighter than the lower
    assert layer.rgb[H // 2 - 3, W // 2].sum() > layer.rgb[H // 2 + 3, W // 2].sum()


def test_the_silhouette_ramp_and_the_z_buffer_of_two_crossing_capsules():
    r, skin = 0.018, np.array([0.7, 0.5, 0.4])  # 2.3 px: the fringe rows 2.5 px off the axis are 30 % covered
    across = Capsules(np.array([[-0.1, 0.0, 0.0]]), np.array([[0.1, 0.0, 0.0]]), np.array([r]))
    layer = render_hand(across, CAMERA, K, W, H, skin)
    # a ray through row y, v = (y + 0.5 - cy) / f, passes the axis (0.5 m ahead, across the view) at distance
    # 0.5 |v| / sqrt(1 + v^2): coverage clip(0.5 + (r - distance) f / 0.5, 0, 1), a one-pixel ramp at the rim
    v = (np.arange(H) + 0.5 - K[1, 2]) / FOCAL
    ramp = np.clip(0.5 + (r - 0.5 * np.abs(v) / np.sqrt(1 + v * v)) * FOCAL / 0.5, 0.0, 1.0)
    np.testing.assert_allclose(layer.coverage[:, W // 2], ramp, atol=1e-6)
    assert ((ramp > 0.2) & (ramp < 0.4)).sum() == 2 and ((ramp > 0) & (ramp < 1)).sum() == 2  # one on each side
    # a second capsule, upright and 5 cm behind the first: together, each pixel shows the nearer one
    upright = Capsules(np.array([[0.0, 0.05, -0.1]]), np.array([[0.0, 0.05, 0.1]]), np.array([r]))
    behind = render_hand(upright, CAMERA, K, W, H, skin)
    both = render_hand(Capsules(*(np.concatenate(pair) for pair in zip(upright, across))), CAMERA, K, W, H, skin)
    np.testing.assert_array_equal(both.depth, np.minimum(layer.depth, behind.depth))
    np.testing.assert_array_equal(both.coverage, np.maximum(layer.coverage, behind.coverage))
    front = layer.depth < behind.depth
    assert front.sum() > 50 and (~front & np.isfinite(behind.depth)).sum() > 50
    np.testing.assert_array_equal(both.rgb[front], layer.rgb[front])


def test_a_finger_in_front_occludes_and_behind_is_hidden():
    scene = np.full((4, 4, 3), 0.2, np.float32)
    alpha = np.ones((4, 4), np.float32)
    depth = np.full((4, 4), 0.5, np.float32)
    hand_rgb = np.full((4, 4, 3), 0.8, np.float32)
    front = HandLayer(hand_rgb, np.full((4, 4), 0.4, np.float32), np.ones((4, 4), np.float32))
    behind = HandLayer(hand_rgb, np.full((4, 4), 0.6, np.float32), np.ones((4, 4), np.float32))
    background = np.array([1.0, 1.0, 1.0])
    np.testing.assert_array_equal(composite_hand(scene, alpha, depth, background, front), hand_rgb)
    np.testing.assert_array_equal(composite_hand(scene, alpha, depth, background, behind), scene)
    # behind a half-transparent rim the hand replaces the background's share: 0.2 + 0.5 (0.8 - 1.0)
    half = composite_hand(scene, np.full((4, 4), 0.5, np.float32), depth, background, behind)
    np.testing.assert_allclose(half, 0.1, atol=1e-6)
    # where nothing is drawn (depth inf) the hand is in front
    np.testing.assert_array_equal(composite_hand(scene, alpha * 0, np.full((4, 4), np.inf), background, behind),
                                  hand_rgb)



def _composite_hand_reference(scene_rgb, scene_alpha, scene_depth, background, hand):
    """The numpy ``composite_hand`` before the kernel (issue 51)."""
    drawn = hand.coverage > 0
    out = scene_rgb.astype(np.float32).copy()
    cov = hand.coverage[drawn][:, None]
    seen = scene_depth[drawn]
    seen = np.where((seen > 0) & np.isfinite(seen), seen, np.inf)
    front = (hand.depth[drawn] <= seen)[:, None]
    rgb, hand_rgb = out[drawn], hand.rgb[drawn]
    over = cov * hand_rgb + (1.0 - cov) * rgb
    under = rgb + (1.0 - scene_alpha[drawn][:, None]) * cov * (hand_rgb - np.asarray(background, np.float32))
    out[drawn] = np.where(front, over, under)
    return out


def test_the_compositing_kernel_equals_the_numpy_formulation_bit_for_bit():
    rng = np.random.default_rng(7)
    h, w = 48, 40
    scene = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
    alpha = rng.uniform(0, 1, (h, w)).astype(np.float32)
    depth = rng.uniform(0.3, 0.7, (h, w)).astype(np.float32)
    depth[rng.uniform(0, 1, (h, w)) < 0.1] = np.inf  # nothing drawn there: 0 or +inf
    depth[rng.uniform(0, 1, (h, w)) < 0.1] = 0.0
    hand_depth = rng.uniform(0.3, 0.7, (h, w)).astype(np.float32)
    ties = rng.uniform(0, 1, (h, w)) < 0.1
    hand_depth[ties] = depth[ties]  # a tie puts the hand in front
    coverage = np.where(rng.uniform(0, 1, (h, w)) < 0.5, rng.uniform(0, 1, (h, w)), 0.0).astype(np.float32)
    coverage[:5] = 0.0  # rows and columns without the hand
    coverage[:, -3:] = 0.0
    coverage[rng.uniform(0, 1, (h, w)) < 0.05] = 1.0
    layer = HandLayer(rng.uniform(0, 1, (h, w, 3)).astype(np.float32), hand_depth, coverage)
    background = np.array([0.9, 0.95, 1.0], np.float32)
    out = composite_hand(scene, alpha, depth, background, layer)
    expected = _composite_hand_reference(scene, alpha, depth, background, layer)
    assert out.dtype == np.float32 and out.shape == scene.shape
    np.testing.assert_array_equal(out, expected)
    front = (hand_depth <= np.where((depth > 0) & np.isfinite(depth), depth, np.inf)) & (coverage > 0)
    assert 100 < front.sum() < (coverage > 0).sum() - 100 and (front & ties).sum() > 10
    np.testing.assert_array_equal(out[coverage == 0], scene[coverage == 0])  # no coverage: the scene untouched
    # an empty hand layer leaves the frame as it is
    empty = HandLayer(layer.rgb, hand_depth, np.zeros((h, w), np.float32))
    np.testing.assert_array_equal(composite_hand(scene, alpha, depth, background, empty), scene)


def test_compositing_at_full_and_no_coverage_in_front_of_and_behind_the_scene():
    """Closed forms: coverage 1 in front = the hand; behind an opaque scene = the scene; behind a scene of opacity
    a = scene + (1 - a)(hand - background); coverage 0 = the scene, whatever the depths."""
    scene = np.full((6, 8, 3), 0.25, np.float32)
    alpha = np.full((6, 8), 1.0, np.float32)
    alpha[:, 4:] = 0.5
    depth = np.full((6, 8), 0.5, np.float32)
    hand_rgb = np.full((6, 8, 3), 0.75, np.float32)
    hand_depth = np.where(np.arange(6)[:, None] < 3, 0.25, 1.0).astype(np.float32) * np.ones((1, 8), np.float32)
    coverage = np.ones((6, 8), np.float32)
    coverage[:, 0] = 0.0
    background = np.array([1.0, 1.0, 1.0], np.float32)
    out = composite_hand(scene, alpha, depth, background, HandLayer(hand_rgb, hand_depth, coverage))
    np.testing.assert_array_equal(out[:3, 1:], 0.75)  # in front: the hand
    np.testing.assert_array_equal(out[3:, 1:4], 0.25)  # behind the opaque object: hidden
    np.testing.assert_array_equal(out[3:, 4:], np.float32(0.25) + np.float32(0.5) * np.float32(-0.25))  # 0.125
    np.testing.assert_array_equal(out[:, 0], 0.25)  # no coverage



def test_the_fused_skin_and_compositing_pass_equals_the_layer_then_the_compositing_bit_for_bit():
    """``draw_hand`` (one kernel pass from the capsules' float64 buffers) = ``composite_hand`` of ``render_hand``'s
    float32 layer, on random capsules in front of, through and behind a random scene (half of it empty)."""
    rng = np.random.default_rng(11)
    n = 12
    a = rng.uniform([-0.12, -0.1, -0.12], [0.12, 0.1, 0.12], (n, 3))
    caps = Capsules(a, a + rng.normal(0, 0.05, (n, 3)), rng.uniform(0.008, 0.02, n))
    skin, background = np.array([0.8, 0.55, 0.45]), np.array([0.9, 0.95, 1.0], np.float32)
    scene = rng.uniform(0, 1, (H, W, 3)).astype(np.float32)
    alpha = rng.uniform(0, 1, (H, W)).astype(np.float32)
    depth = rng.uniform(0.42, 0.58, (H, W)).astype(np.float32)  # the capsules' fronts lie between 0.38 and 0.62 m
    depth[:, : W // 2] = np.where(rng.uniform(0, 1, (H, W // 2)) < 0.5, np.inf, 0.0)
    layer = render_hand(caps, CAMERA, K, W, H, skin)
    expected = composite_hand(scene, alpha, depth, background, layer)
    out = draw_hand(caps, CAMERA, K, skin, scene, alpha, depth, background)
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out, expected)
    covered = layer.coverage > 0
    front = layer.depth <= np.where((depth > 0) & np.isfinite(depth), depth, np.inf)
    assert (covered & front).sum() > 200 and (covered & ~front).sum() > 50
    assert ((layer.coverage > 0) & (layer.coverage < 1)).sum() > 50  # the anti-aliased rim
    nothing = Capsules(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
    np.testing.assert_array_equal(draw_hand(nothing, CAMERA, K, skin, scene, alpha, depth, background), scene)


def test_a_finger_chain_ends_at_the_recorded_tip_with_its_bone_lengths_and_bends_more_when_closer():
    knuckle, length = np.zeros(3), 0.08
    bends = []
    for d in (0.07, 0.05):
        tip = np.array([d, 0.0, 0.0])
        joints = finger_chain(knuckle, tip, length, 0.5, np.array([0.0, 0.0, 1.0]))
        np.testing.assert_allclose(joints[-1], tip, atol=1e-9)
        np.testing.assert_allclose(np.linalg.norm(np.diff(joints, axis=0), axis=1).sum(), length, rtol=1e-6)
        assert (joints[1:3, 2] > 0).all()  # the bend bulges towards the given side
        bends.append(joints[1:3, 2].max())
    assert bends[1] > bends[0]
    # a tip beyond reach: a straight finger to it
    far = finger_chain(knuckle, np.array([0.1, 0.0, 0.0]), length, 0.5, np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(far[:, 1:], 0.0, atol=1e-12)


def test_the_drawn_fingertips_follow_the_recording_frame_by_frame():
    """A lifted finger (its recorded tip moving away) is drawn lifted: every finger's last capsule ends at its
    recorded tip in every frame, whatever the simulation did."""
    n = 5
    rng = np.random.default_rng(0)
    tips0 = np.array([[-0.04, 0.0, 0.005], [0.04, 0.0, 0.015], [0.04, 0.0, 0.005], [0.04, 0.0, -0.005],
                      [0.04, 0.0, -0.015]])
    tips = np.repeat(tips0[None], n, 0) + rng.normal(0, 0.001, (n, 5, 3))
    tips[:, 1, 0] += np.linspace(0.0, 0.03, n)  # the index finger lifts off
    q = np.array([np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)])  # palm z (towards the object) = +y
    signals = {"fingertip_positions": tips, "palm_position": np.tile([0.0, -0.05, 0.0], (n, 1)),
               "palm_orientation": np.tile(q, (n, 1)), "flexion": np.full((n, 5), 0.4),
               "grasp_centre": np.zeros((n, 3))}
    hands = hand_sequence(signals, np.arange(n))
    for f, caps in enumerate(hands):
        np.testing.assert_allclose(caps.b[2:15:3], tips[f], atol=1e-9)  # distal phalanges end at the tips


def _shade_skin_reference(normal, colour, view):
    """The numpy ``shade_skin`` before the kernel (issue 51): normal, view (n, 3)."""
    def unit(v):
        return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)
    light = unit(np.array([-0.4, -0.7, -0.6]))
    n_l = np.clip(normal @ light, 0.0, None)[..., None]
    half = unit(light - view)
    spec = 0.12 * np.clip(np.sum(normal * half, axis=-1), 0.0, None)[..., None] ** 24
    return np.clip(np.asarray(colour) * (0.38 + 0.62 * n_l) + spec, 0.0, 1.0)


def test_the_skin_shading_kernel_equals_the_numpy_formulation_within_round_off():
    rng = np.random.default_rng(5)
    normal = rng.normal(size=(3, 48, 40))
    normal /= np.linalg.norm(normal, axis=0)
    normal[2] = -np.abs(normal[2])  # facing the camera, lit and unlit sides
    view = np.stack(np.broadcast_arrays((np.arange(40) + 0.5 - 20) / 50.0, ((np.arange(48) + 0.5 - 24) / 50.0)[:, None],
                                        np.ones((1, 1))))
    view /= np.linalg.norm(view, axis=0)
    coverage = np.where(rng.uniform(0, 1, (48, 40)) < 0.6, rng.uniform(0.01, 1.0, (48, 40)), 0.0)
    colour = np.array([0.8, 0.55, 0.45])
    rgb = shade_skin(normal, colour, view, coverage)
    drawn = coverage > 0
    expected = _shade_skin_reference(np.moveaxis(normal, 0, -1)[drawn], colour, np.moveaxis(view, 0, -1)[drawn])
    assert rgb.dtype == np.float32 and rgb.shape == (48, 40, 3)
    assert np.array_equal(rgb[~drawn], np.zeros(((~drawn).sum(), 3), np.float32))
    # numpy's n.l is a BLAS product (fused multiply-adds), its power SVML's: float64 round-off, then float32
    assert np.abs(rgb[drawn] - expected).max() <= 1.2e-7
    assert (rgb[drawn] == expected.astype(np.float32)).mean() > 0.999
    assert expected[..., 0].max() - expected[..., 0].min() > 0.3  # lit and unlit sides, sheen


def test_a_sphere_seen_at_its_centre_has_the_closed_form_skin_shade():
    k = np.array([[FOCAL, 0.0, 32.5], [0.0, FOCAL, 32.5], [0.0, 0.0, 1.0]])  # pixel (32, 32) on the optical axis
    viewmat = np.eye(4)  # camera = world: x right, y down, z forward
    centre, r, skin = np.array([0.0, 0.0, 0.5]), 0.05, np.array([0.7, 0.5, 0.4])
    layer = render_hand(Capsules(centre[None], centre[None], np.array([r])), viewmat, k, W, H, skin)
    assert layer.depth[32, 32] == np.float32(0.5 - r) and layer.coverage[32, 32] == 1.0
    # there the normal is (0, 0, -1) and the view direction (0, 0, 1): n.l = -l_z, n.h = -h_z, h = unit(l - v)
    light = np.array([-0.4, -0.7, -0.6]) / np.linalg.norm([-0.4, -0.7, -0.6])
    half = (light - [0.0, 0.0, 1.0]) / np.linalg.norm(light - [0.0, 0.0, 1.0])
    expected = skin * (0.38 + 0.62 * -light[2]) + 0.12 * (-half[2]) ** 24
    np.testing.assert_allclose(layer.rgb[32, 32], expected, atol=1e-7)
    assert (layer.rgb[32, 32] > layer.rgb[32 + 4, 32 + 4]).all()  # lit from the upper left
