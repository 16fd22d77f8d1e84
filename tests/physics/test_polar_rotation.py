"""The tracers' polar rotation (recorded every frame as the Gaussians' rotations): the Newton iteration agrees with
the SVD's proper rotation, and the rows it cannot take (reflections, singular or ill-conditioned F) go to the SVD."""
import numpy as np

from tasks.physics.mpm.tracers import _polar_svd, polar_rotation


def _rotation(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def test_known_rotation_of_a_stretch():
    """F = R S with S symmetric positive definite: R comes back to round-off."""
    R = _rotation([1, 2, 3], 0.7)
    S = np.array([[2.0, 0.3, 0.0], [0.3, 0.5, 0.1], [0.0, 0.1, 1.2]])
    out = polar_rotation((R @ S)[None])[0]
    assert np.abs(out - R).max() < 1e-14


def test_matches_the_svd_on_every_kind_of_row():
    rng = np.random.default_rng(3)
    F = np.eye(3) + 0.4 * rng.standard_normal((400, 3, 3))
    F[:5] = -F[:5]  # reflections (det < 0): the SVD's flipped proper rotation
    F[5] = np.diag([1.0, 1.0, 1e-9])  # ill-conditioned
    F[6] = 0.0  # singular
    R = polar_rotation(F)
    assert np.abs(R - _polar_svd(F)).max() < 1e-12
    assert np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max() < 1e-13
    assert np.linalg.det(R).min() > 1 - 1e-12
    assert polar_rotation(np.zeros((0, 3, 3))).shape == (0, 3, 3)
