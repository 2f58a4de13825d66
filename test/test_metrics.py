"""Metric definitions (RPM-Net / DCP) against hand-computed values."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cegc_ros import metrics as M


def rot(axis: str, deg: float) -> np.ndarray:
    return Rotation.from_euler(axis, deg, degrees=True).as_matrix()


def transform(R: np.ndarray = np.eye(3), t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def test_euler_of_single_axis_rotations():
    assert M.euler_xyz_deg(rot("z", 30)) == pytest.approx([0, 0, 30])
    assert M.euler_xyz_deg(rot("x", -20)) == pytest.approx([-20, 0, 0])
    assert M.euler_xyz_deg(rot("y", 45)) == pytest.approx([0, 45, 0])


def test_euler_is_extrinsic_xyz_as_scipy():
    # R = Rz(c) Ry(b) Rx(a): x applied first, about fixed axes.
    R = rot("z", 30) @ rot("y", 20) @ rot("x", 10)
    assert M.euler_xyz_deg(R) == pytest.approx([10, 20, 30])
    Rs = Rotation.random(200, random_state=1).as_matrix()
    expected = Rotation.from_matrix(Rs).as_euler("xyz", degrees=True)
    np.testing.assert_allclose(M.euler_xyz_deg(Rs), expected, atol=1e-9)


@pytest.mark.filterwarnings("ignore:Gimbal lock")
@pytest.mark.parametrize("angles", [(10, 90, 30), (10, -90, 30), (-70, 90, 0)])
def test_euler_gimbal_lock_matches_scipy(angles):
    R = Rotation.from_euler("xyz", angles, degrees=True).as_matrix()
    expected = Rotation.from_matrix(R).as_euler("xyz", degrees=True)
    np.testing.assert_allclose(M.euler_xyz_deg(R), expected, atol=1e-6)


def test_isotropic_errors():
    R_gt = rot("xyz", [5, -30, 60])
    assert M.rotation_error_deg(R_gt, R_gt @ rot("x", 7)) == pytest.approx(7)
    assert M.rotation_error_deg(R_gt, R_gt) == pytest.approx(0, abs=1e-6)
    assert M.rotation_error_deg(np.eye(3), rot("y", 180)) == pytest.approx(180)
    assert M.translation_error([1, 2, 3], [1.3, 2.4, 3]) == pytest.approx(0.5)


def test_summary_two_pairs_hand_computed():
    # Pair A: truth identity, estimate Rz(30) and t = (0.3, 0.4, 0).
    #   Euler diff (0, 0, -30); t diff (-0.3, -0.4, 0); Error(R) 30; Error(t) 0.5.
    # Pair B: truth Rx(10), t (1, 0, 0); estimate exact.
    T_gt = np.stack([transform(), transform(rot("x", 10), (1, 0, 0))])
    T_est = np.stack([transform(rot("z", 30), (0.3, 0.4, 0)), T_gt[1]])
    s = M.summarize(T_gt, T_est, thresholds=M.SEVEN_SCENES_RECALL)
    assert s["rmse_r"] == pytest.approx(math.sqrt(30**2 / 6))       # 12.247
    assert s["mae_r"] == pytest.approx(30 / 6)                      # 5.0
    assert s["rmse_t"] == pytest.approx(math.sqrt((0.09 + 0.16) / 6))  # 0.2041
    assert s["mae_t"] == pytest.approx(0.7 / 6)                     # 0.1167
    assert s["error_r"] == pytest.approx(15.0)
    assert s["error_t"] == pytest.approx(0.25)
    assert s["recall"] == pytest.approx(0.5)
    assert (s["n_pairs"], s["n_success"], s["n_invalid"], s["n_exception"]) == (2, 1, 0, 0)


def test_euler_difference_is_not_wrapped_as_in_rpmnet():
    s = M.summarize(transform(rot("z", 170))[None], transform(rot("z", -170))[None])
    assert s["mae_r"] == pytest.approx(340 / 3)
    assert s["error_r"] == pytest.approx(20)


def test_failures_count_and_are_scored_as_identity():
    T_gt = np.stack([transform(rot("z", 40), (0, 0, 0.5))] * 3)
    garbage = np.full((4, 4), np.nan)
    T_est = np.stack([T_gt[0], T_gt[0], garbage])
    s = M.summarize(T_gt, T_est, valid=[True, False, True], raised=[False, False, True])
    # Pair 2 raised: identity is scored (Error(R) 40, Error(t) 0.5); pair 1 is exact but invalid.
    assert s["error_r"] == pytest.approx(40 / 3)
    assert s["error_t"] == pytest.approx(0.5 / 3)
    assert s["recall"] == pytest.approx(1 / 3)
    assert (s["n_success"], s["n_invalid"], s["n_exception"]) == (1, 1, 1)


def test_real_fragment_recall_needs_translation_too():
    T_gt = np.stack([transform(), transform()])
    T_est = np.stack([transform(rot("x", 10), (0.2, 0, 0)), transform(rot("x", 10), (0.4, 0, 0))])
    assert M.summarize(T_gt, T_est, thresholds=M.REAL_FRAGMENT_RECALL)["recall"] == pytest.approx(0.5)
    assert M.summarize(T_gt, T_est, thresholds=M.SEVEN_SCENES_RECALL)["recall"] == 0.0


def test_within_one_estimate_agrees_with_the_recall_of_summarize():
    T_gt = transform(rot("z", 30), (1.0, 2.0, 0.5))
    for angle, shift, real, seven in [(10, 0.2, True, False), (10, 0.4, False, False),
                                      (16, 0.0, False, False), (4, 0.4, False, True)]:
        T_est = T_gt @ transform(rot("x", angle), (0, 0, 0))
        T_est[:3, 3] += (shift, 0, 0)
        assert M.within(T_gt, T_est) is real
        assert M.within(T_gt, T_est, M.SEVEN_SCENES_RECALL) is seven
        assert M.summarize(T_gt[None], T_est[None], thresholds=M.REAL_FRAGMENT_RECALL)["recall"] == float(real)


def test_bad_shapes_raise():
    with pytest.raises(ValueError):
        M.pair_errors(np.eye(3), np.eye(3))
    with pytest.raises(ValueError):
        M.summarize(np.zeros((0, 4, 4)))
