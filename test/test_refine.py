"""The engine's Open3D stages on the tensor pipeline: the same numbers as the legacy pipeline the
network was trained with (features) and the engine used before (ICP)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cegc_ros.geometry import normals_and_fpfh
from cegc_ros.metrics import rotation_error_deg
from cegc_ros.refine import icp


def room_corner(n: int, seed: int) -> np.ndarray:
    """(n, 3) noisy samples of a floor, two walls and a box: a 3 m corner of a room."""
    rng = np.random.default_rng(seed)
    k = n // 4
    floor = np.c_[rng.uniform(0, 3, (k, 2)), np.zeros(k)]
    wall_x = np.c_[np.zeros(k), rng.uniform(0, 3, k), rng.uniform(0, 2.5, k)]
    wall_y = np.c_[rng.uniform(0, 3, k), np.zeros(k), rng.uniform(0, 2.5, k)]
    u = rng.uniform(0, 0.6, (n - 3 * k, 2))
    box = np.c_[1.2 + u[:, 0], 1.0 + u[:, 1], np.full(len(u), 0.6)]       # a box's top
    return np.concatenate([floor, wall_x, wall_y, box]) + rng.normal(0, 0.003, (n, 3))


def legacy_icp(source, target, T, max_distance, iterations):
    import open3d as o3d
    reg = o3d.pipelines.registration
    ps = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source))
    pt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target))
    pt.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.0 * max_distance, max_nn=30))
    return np.asarray(reg.registration_icp(ps, pt, max_distance, T, reg.TransformationEstimationPointToPlane(),
                                           reg.ICPConvergenceCriteria(max_iteration=iterations)).transformation)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_icp_gives_the_legacy_pipelines_pose_and_recovers_the_truth(seed):
    target = room_corner(4000, seed)
    T_true = np.eye(4)
    T_true[:3, :3] = Rotation.from_rotvec([0.01, -0.02, 0.03]).as_matrix()
    T_true[:3, 3] = [0.03, -0.02, 0.01]
    source = (target - T_true[:3, 3]) @ T_true[:3, :3]            # T_true maps source onto target
    source = source + np.random.default_rng(seed + 10).normal(0, 0.002, source.shape)
    start = np.eye(4)
    T = icp(source, target, start, 0.1, 30, max_points=10000)
    assert np.abs(T - legacy_icp(source, target, start, 0.1, 30)).max() < 1e-9
    assert rotation_error_deg(T_true[:3, :3], T[:3, :3]) < 0.1
    assert np.linalg.norm(T[:3, 3] - T_true[:3, 3]) < 0.005
    # far from the truth nothing within reach: ICP leaves the start alone or moves little
    assert np.isfinite(icp(source, target + 50.0, start, 0.1, 30, max_points=10000)).all()


def test_icp_on_a_plane_keeps_the_start_and_the_engine_registers_a_floor():
    """Point-to-plane ICP cannot pin a plane's in-plane motion: Open3D's tensor ICP raises on
    its singular system; icp returns the start pose, and the engine registers two views of a
    flat floor (the pose from its estimator) instead of raising."""
    from cegc_ros.engine import Registrar
    rng = np.random.default_rng(0)
    floor = np.c_[rng.uniform(0, 2, (3000, 2)), np.zeros(3000)]
    T = np.eye(4)
    T[:3, 3] = [0.01, -0.02, 0.0]
    np.testing.assert_array_equal(icp(floor, floor, T, 0.05, 30, 5000), T)
    res = Registrar.from_checkpoint(device="cpu").register(floor[:2000], floor[1000:] + [0.1, 0.0, 0.0])
    assert np.isfinite(res.T_target_source).all() and res.refined in ("icp", "none")
    assert abs(res.T_target_source[2, 3]) < 0.05                 # stays on the floor


def test_features_match_the_legacy_pipeline_the_network_was_trained_on():
    import open3d as o3d
    pts = room_corner(1024, 3) / 6.0                                 # normalised-frame size
    normals, desc = normals_and_fpfh(pts)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.10, max_nn=30))
    n = np.asarray(pcd.normals)
    n[((pts.mean(0) - pts) * n).sum(1) < 0] *= -1.0
    pcd.normals = o3d.utility.Vector3dVector(n)
    ref = np.asarray(o3d.pipelines.registration.compute_fpfh_feature(
        pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=0.25, max_nn=200)).data).T / 100.0
    assert desc.shape == (1024, 33) and normals.shape == (1024, 3)
    assert np.abs(normals - n).max() < 1e-5                           # same orientation too
    np.testing.assert_allclose(desc.reshape(-1, 3, 11).sum(2), 2.0, atol=1e-4)   # 3 histograms
    np.testing.assert_allclose(ref.reshape(-1, 3, 11).sum(2), 2.0, atol=1e-4)
    row = np.abs(desc - ref).sum(1)                                   # L1 of a row of mass 6
    assert np.median(row) < 1e-3 and row.mean() < 0.005               # rounding at bin edges
    cosine = (desc * ref).sum(1) / np.linalg.norm(desc, axis=1) / np.linalg.norm(ref, axis=1)
    assert cosine.min() > 0.9999


def test_fitnesses_count_exactly_the_points_within_the_distance():
    """The batched k-d-tree fitness (its search bounded at the distance itself) against brute
    force, with source points placed exactly at the distance from a target point."""
    from scipy.spatial.distance import cdist

    from cegc_ros.refine import fitnesses
    rng = np.random.default_rng(3)
    target = rng.uniform(0, 1, (300, 3))
    source = np.concatenate([target[:100] + rng.normal(0, 0.01, (100, 3)),
                             target[100:150] + [0.05, 0.0, 0.0],        # exactly at 0.05 m
                             rng.uniform(0, 1, (150, 3))])
    R = Rotation.from_rotvec(rng.normal(0, 0.02, (6, 3))).as_matrix()
    R[0] = np.eye(3)
    t = rng.normal(0, 0.01, (6, 3))
    t[0] = 0.0
    got = fitnesses(R, t, source, target, 0.05)
    moved = source[None] @ np.transpose(R, (0, 2, 1)) + t[:, None]
    expected = np.array([(cdist(m, target).min(1) <= 0.05).mean() for m in moved])
    np.testing.assert_array_equal(got, expected)
    assert got[0] > 0.45                 # the 100 near points and the boundary ones that round inside


def test_feature_agreement_sums_the_cosines_of_the_points_a_pose_brings_together():
    """refine.landing_evidence's agreement against a loop over the points: for each source point within
    the distance of its nearest target point under the pose, that pair's cosine (from the
    similarity matrix), summed and floored at 0 per pose; its fitness is refine.fitnesses'."""
    from scipy.spatial import cKDTree

    from cegc_ros.refine import fitnesses, landing_evidence

    def fitness_agreements(R, t, source, target, similarity, distance):
        return landing_evidence(R, t, source, target, similarity, np.ones(len(source)), distance)[:2]
    rng = np.random.default_rng(5)
    src, tgt = rng.uniform(0, 1, (300, 3)), rng.uniform(0, 1, (250, 3))
    ds, dt = rng.normal(size=(300, 8)), rng.normal(size=(250, 8))
    ds /= np.linalg.norm(ds, axis=1, keepdims=True)
    dt /= np.linalg.norm(dt, axis=1, keepdims=True)
    R = Rotation.from_euler("xyz", rng.uniform(-10, 10, (6, 3)), degrees=True).as_matrix()
    t = rng.normal(0, 0.05, (6, 3))
    fit, got = fitness_agreements(R, t, src, tgt, ds @ dt.T, 0.06)
    np.testing.assert_array_equal(fit, fitnesses(R, t, src, tgt, 0.06))
    for h in range(6):
        d, j = cKDTree(tgt).query(src @ R[h].T + t[h])
        expect = sum(float(ds[i] @ dt[j[i]]) for i in range(len(src)) if d[i] <= 0.06)
        assert got[h] == pytest.approx(max(expect, 0.0), rel=1e-5, abs=1e-5)
        assert fit[h] == pytest.approx(float((d <= 0.06).mean()))
    assert (got > 0).any() and (fit > 0.1).all()
    # the same descriptors at the same places: every point agrees fully under the identity
    one = (np.eye(3)[None], np.zeros((1, 3)))
    assert fitness_agreements(*one, src, src, ds @ ds.T, 1e-6)[1][0] == pytest.approx(300.0, rel=1e-5)
    # opposite descriptors: the sum is negative, floored at 0
    assert fitness_agreements(*one, src, src, -ds @ ds.T, 1e-6)[1][0] == 0.0
