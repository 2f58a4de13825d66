"""refine.covariance / covariance_from_information: symmetric PSD and finite on every input.

The engine's covariance once came out with variances of -7e13 on an AMD CPU (an inverse of a
near-singular J^T W J) and the node rejected the pose. These sets are degenerate on purpose;
the assertions hold whatever the CPU's rounding, because they test the construction (an
eigendecomposition with a floor), not particular digits.
"""

from __future__ import annotations

import numpy as np
import pytest

from cegc_ros.refine import UNCONSTRAINED_VARIANCE, covariance, covariance_from_information
from cegc_ros.sequential.icp import point_to_plane_covariance


def _rot(deg: float) -> np.ndarray:
    a = np.radians(deg)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    T[:3, 3] = [0.3, -0.2, 0.1]
    return T


def _assert_psd(C: np.ndarray) -> np.ndarray:
    assert C.shape == (6, 6) and np.isfinite(C).all()
    assert np.array_equal(C, C.T)
    lam = np.linalg.eigvalsh(C)
    assert lam.min() >= -1e-9 * UNCONSTRAINED_VARIANCE        # PSD up to the rounding of V diag V^T
    assert (np.diag(C) >= 0).all() and np.diag(C).max() <= UNCONSTRAINED_VARIANCE * (1 + 1e-9)
    return lam


def _sets(name: str, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, int]:
    """(src, weights, number of undetermined directions) of one degenerate kind."""
    if name == "collinear":            # rotation about the line is free
        return np.outer(np.linspace(-1, 1, 50), [1.0, 2.0, -0.5]), np.ones(50), 1
    if name == "planar":               # determined (a plane of points fixes all six)
        p = np.c_[rng.uniform(-1, 1, (200, 2)), np.zeros(200)]
        return p, np.ones(200), 0
    if name == "three_points":
        return rng.uniform(-1, 1, (3, 3)), np.ones(3), 0
    if name == "one_point_repeated":   # every rotation is free
        return np.tile([[0.5, -0.2, 1.0]], (40, 1)), np.ones(40), 3
    if name == "very_spread":          # kilometres apart with millimetre-sized detail
        p = rng.uniform(-1, 1, (100, 3)) * [5000.0, 5000.0, 1e-3]
        return p, np.ones(100), 0
    if name == "huge_cloud":           # far from the origin, a near-singular Hessian
        p = rng.uniform(-1, 1, (200_000, 3)) * 1e-3 + [1e5, -3e4, 2e4]
        return p, rng.uniform(0, 1, 200_000), 0
    if name == "zero_weights":
        return rng.uniform(-1, 1, (30, 3)), np.zeros(30), 6
    raise AssertionError(name)


KINDS = ["collinear", "planar", "three_points", "one_point_repeated", "very_spread",
         "huge_cloud", "zero_weights"]


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("noise", [0.0, 1e-3])
def test_covariance_is_symmetric_psd_and_finite_on_degenerate_sets(kind, noise):
    rng = np.random.default_rng(KINDS.index(kind))
    src, w, free = _sets(kind, rng)
    T = _rot(30.0)
    tgt = src @ T[:3, :3].T + T[:3, 3] + rng.normal(0, noise, src.shape)
    lam = _assert_psd(covariance(src, tgt, w, T))
    # Each direction the data do not determine carries the documented large variance.
    assert (lam > 0.5 * UNCONSTRAINED_VARIANCE).sum() >= free


def test_a_free_rotation_about_a_line_gets_the_large_variance_along_that_axis():
    d = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    src = np.outer(np.linspace(-1, 1, 50), d)
    C = covariance(src, src + 1e-3 * np.random.default_rng(0).normal(size=src.shape),
                   np.ones(50), np.eye(4))
    lam, V = np.linalg.eigh(C)
    axis = V[3:, -1] / np.linalg.norm(V[3:, -1])      # rotational part of the largest direction
    assert lam[-1] == pytest.approx(UNCONSTRAINED_VARIANCE, rel=1e-6)
    assert abs(axis @ d) > 0.999
    assert lam[-2] < 1.0                               # the other five are determined


def test_a_well_determined_set_matches_the_plain_inverse():
    rng = np.random.default_rng(1)
    src = rng.uniform(-1, 1, (300, 3))
    T = _rot(10.0)
    tgt = src @ T[:3, :3].T + T[:3, 3] + rng.normal(0, 0.01, src.shape)
    C = covariance(src, tgt, np.ones(300), T)
    rp = src @ T[:3, :3].T
    J = np.zeros((300, 3, 6))
    J[:, :, :3] = np.eye(3)
    J[:, 0, 4], J[:, 0, 5], J[:, 1, 3] = rp[:, 2], -rp[:, 1], -rp[:, 2]      # -[R p]x
    J[:, 1, 5], J[:, 2, 3], J[:, 2, 4] = rp[:, 0], rp[:, 1], -rp[:, 0]
    H = np.einsum("nij,nik->jk", J, J)
    res = rp + T[:3, 3] - tgt
    ref = np.linalg.inv(H) * (res ** 2).sum() / (3 * 300)
    np.testing.assert_allclose(C, ref, rtol=1e-8, atol=1e-14)
    assert np.diag(C)[:3].max() < 1e-5


def test_information_with_negative_or_non_finite_eigenvalues_stays_psd():
    V = np.linalg.qr(np.random.default_rng(2).normal(size=(6, 6)))[0]
    H = (V * np.array([-1e-3, 1e-20, 1.0, 2.0, 3.0, 4.0])) @ V.T      # rounding made one < 0
    lam = _assert_psd(covariance_from_information(H, 0.5))
    assert (lam > 0.5 * UNCONSTRAINED_VARIANCE).sum() == 2
    np.testing.assert_allclose(np.sort(lam)[:4], [0.5 / 4, 0.5 / 3, 0.5 / 2, 0.5], rtol=1e-6)
    bad = np.eye(6)
    bad[0, 0] = np.nan
    assert np.array_equal(covariance_from_information(bad, 1.0), np.diag([UNCONSTRAINED_VARIANCE] * 6))


def test_point_to_plane_covariance_of_a_corridor_is_psd_with_its_free_direction():
    rng = np.random.default_rng(3)
    # Two parallel walls (normals +-y) and a floor (normal z): translation along x is free.
    n = 300
    walls = np.c_[rng.uniform(-5, 5, n), np.where(rng.random(n) < 0.5, -1.0, 1.0), rng.uniform(0, 2, n)]
    floor = np.c_[rng.uniform(-5, 5, n), rng.uniform(-1, 1, n), np.zeros(n)]
    pts = np.concatenate([walls, floor])
    normals = np.concatenate([np.c_[np.zeros(n), -np.sign(walls[:, 1]), np.zeros(n)],
                              np.tile([0.0, 0.0, 1.0], (n, 1))])
    C = point_to_plane_covariance(pts, normals, rng.normal(0, 0.01, 2 * n))
    lam, V = np.linalg.eigh(C)
    _assert_psd(C)
    assert lam[-1] == pytest.approx(UNCONSTRAINED_VARIANCE, rel=1e-6)
    assert abs(V[0, -1]) > 0.999                        # the free direction is x translation
