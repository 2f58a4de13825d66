"""Registration error metrics, defined exactly as RPM-Net and DCP report them (numpy only).

All transforms are ``T_target_source`` (4, 4): they map source points into the target frame,
``p_t = R p_s + t``. Units: degrees for rotations, the clouds' unit (metres) for translations.

Per pair (ground truth ``R_gt, t_gt``; estimate ``R, t``):

* **Euler differences** ``e_gt - e`` (3,), where ``e = euler_xyz_deg(R)`` are the angles that
  ``scipy.spatial.transform.Rotation.from_matrix(R).as_euler('xyz', degrees=True)`` returns:
  lower-case ``'xyz'`` is *extrinsic* x, then y, then z, i.e. ``R = Rz(c) Ry(b) Rx(a)``.
  This is RPM-Net's ``dcm2euler(..., seq='xyz')`` (``eval.py: compute_metrics``); DCP's
  ``npmat2euler`` uses the same scipy call with ``seq='zyx'`` on its own generated angles.
  As in RPM-Net the difference is *not* wrapped to (-180, 180].
* **Translation differences** ``t_gt - t`` (3,).
* **Isotropic rotation error** ``arccos((tr(R_gt^T R) - 1) / 2)`` in degrees (argument clipped
  to [-1, 1]) and **isotropic translation error** ``|t_gt - t|`` (RPM-Net's ``err_r_deg`` and
  ``err_t``; ``|R_gt^T (t - t_gt)| = |t - t_gt|``).

Over K pairs (RPM-Net's ``summarize_metrics``):

* ``RMSE(R) = sqrt(mean over pairs and the 3 axes of (e_gt - e)^2)``; ``MAE(R)`` = mean of
  ``|e_gt - e|`` over pairs and axes; ``RMSE(t)`` and ``MAE(t)`` the same over translation
  components;
* ``Error(R)`` and ``Error(t)``: means over pairs of the isotropic errors;
* ``recall``: fraction of *all* pairs that succeeded (no exception, valid result) with
  ``Error(R) < rot_threshold`` and, when a translation threshold is given,
  ``Error(t) < trans_threshold``. Thresholds used in this project: 5 deg for the synthetic
  7Scenes protocol (``SEVEN_SCENES_RECALL``); 15 deg and 0.3 m on real fragment pairs
  (``REAL_FRAGMENT_RECALL``, the 3DMatch-style tolerance of the ground truth).

Failures: a pair on which a method raised has no estimate; :func:`summarize` scores it with the
identity transform (the "did not move" answer) so that every method is averaged over the same
pairs, and counts it as a failure in ``recall``. A pair whose result was returned but flagged
invalid keeps its estimate in the error averages and is also a recall failure. Both counts are
reported (``n_exception``, ``n_invalid``), never dropped.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class RecallThresholds:
    """When a registration counts as a success: isotropic errors below these bounds."""

    rot_deg: float
    trans: float | None = None  # None: rotation only

    def describe(self) -> str:
        if self.trans is None:
            return f"Error(R) < {self.rot_deg:g} deg"
        return f"Error(R) < {self.rot_deg:g} deg and Error(t) < {self.trans:g} m"


SEVEN_SCENES_RECALL = RecallThresholds(rot_deg=5.0)
REAL_FRAGMENT_RECALL = RecallThresholds(rot_deg=15.0, trans=0.3)


def _as_rotations(R: np.ndarray) -> np.ndarray:
    R = np.asarray(R, dtype=np.float64)
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"expected rotation matrices of shape (..., 3, 3), got {R.shape}")
    return R


def _as_transforms(T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape[-2:] != (4, 4):
        raise ValueError(f"expected transforms of shape (..., 4, 4), got {T.shape}")
    return T


def euler_xyz_deg(R: np.ndarray) -> np.ndarray:
    """Extrinsic xyz Euler angles in degrees of rotation matrices (..., 3, 3) -> (..., 3).

    Same result as scipy's ``Rotation.from_matrix(R).as_euler('xyz', degrees=True)``, i.e.
    ``R = Rz(c) @ Ry(b) @ Rx(a)`` with ``b`` in [-90, 90]; in gimbal lock (``|b| = 90``)
    scipy's choice is kept: ``c = 0``.
    """
    R = _as_rotations(R)
    sin_b = np.clip(-R[..., 2, 0], -1.0, 1.0)
    b = np.arcsin(sin_b)
    a = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    c = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    # Gimbal lock: R[2,0] = -+1; with c = 0, R = Ry(+-90) Rx(a): a = atan2(+-R[0,1], R[1,1]).
    lock = np.abs(np.abs(sin_b) - 1.0) < 1e-7
    if np.any(lock):
        a_lock = np.arctan2(np.sign(sin_b) * R[..., 0, 1], R[..., 1, 1])
        a = np.where(lock, a_lock, a)
        c = np.where(lock, 0.0, c)
    return np.degrees(np.stack([a, b, c], axis=-1))


def rotation_error_deg(R_gt: np.ndarray, R_est: np.ndarray) -> np.ndarray:
    """Isotropic rotation error arccos((tr(R_gt^T R_est) - 1) / 2) in degrees, (..., 3, 3) -> (...)."""
    R_gt, R_est = _as_rotations(R_gt), _as_rotations(R_est)
    trace = np.einsum("...ji,...ji->...", R_gt, R_est)  # tr(R_gt^T R_est)
    return np.degrees(np.arccos(np.clip((trace - 1.0) / 2.0, -1.0, 1.0)))


def translation_error(t_gt: np.ndarray, t_est: np.ndarray) -> np.ndarray:
    """Isotropic translation error |t_gt - t_est|, (..., 3) -> (...)."""
    return np.linalg.norm(np.asarray(t_gt, np.float64) - np.asarray(t_est, np.float64), axis=-1)


def within(T_gt: np.ndarray, T_est: np.ndarray,
           thresholds: RecallThresholds = REAL_FRAGMENT_RECALL) -> bool:
    """One estimate (4, 4) against its ground truth (4, 4): are its isotropic errors below
    ``thresholds`` (default 15 deg / 0.3 m)? Validity is the caller's to add."""
    T_gt, T_est = np.asarray(T_gt, np.float64), np.asarray(T_est, np.float64)
    if rotation_error_deg(T_gt[:3, :3], T_est[:3, :3]) >= thresholds.rot_deg:
        return False
    if thresholds.trans is None:
        return True
    return bool(translation_error(T_gt[:3, 3], T_est[:3, 3]) < thresholds.trans)


@dataclass
class PairErrors:
    """Errors of K estimates against their ground truths (arrays over pairs)."""

    euler_diff_deg: np.ndarray  # (K, 3) euler_xyz(R_gt) - euler_xyz(R_est)
    trans_diff: np.ndarray      # (K, 3) t_gt - t_est
    rot_error_deg: np.ndarray   # (K,) isotropic
    trans_error: np.ndarray     # (K,) isotropic


def rank_auc(scores: np.ndarray, true: np.ndarray) -> float:
    """The chance that a true item scores above a false one (ties count half), scores (N,)
    against boolean true (N,); NaN without both classes. How well a confidence ranks: the
    overlap estimate's points, the correspondences' confidences (select_weights, the trainer's
    log)."""
    true = np.asarray(true, bool)
    P, N = int(true.sum()), int((~true).sum())
    if not (P and N):
        return float("nan")
    from scipy.stats import rankdata
    r = rankdata(scores)                                                 # ties share their mean rank
    return float((r[true].sum() - P * (P + 1) / 2) / (P * N))


def pair_errors(T_gt: np.ndarray, T_est: np.ndarray) -> PairErrors:
    """Per-pair errors of estimates (K, 4, 4) against ground truths (K, 4, 4) (or single (4, 4))."""
    T_gt = _as_transforms(T_gt).reshape(-1, 4, 4)
    T_est = _as_transforms(T_est).reshape(-1, 4, 4)
    if T_gt.shape != T_est.shape:
        raise ValueError(f"ground truth {T_gt.shape} and estimates {T_est.shape} differ in count")
    R_gt, t_gt = T_gt[:, :3, :3], T_gt[:, :3, 3]
    R_est, t_est = T_est[:, :3, :3], T_est[:, :3, 3]
    return PairErrors(
        euler_diff_deg=euler_xyz_deg(R_gt) - euler_xyz_deg(R_est),
        trans_diff=t_gt - t_est,
        rot_error_deg=rotation_error_deg(R_gt, R_est),
        trans_error=translation_error(t_gt, t_est),
    )


def success_mask(errors: PairErrors, ok: np.ndarray, thresholds: RecallThresholds) -> np.ndarray:
    """(K,) bool: pair succeeded (``ok``) and its isotropic errors are within the thresholds."""
    hit = errors.rot_error_deg < thresholds.rot_deg
    if thresholds.trans is not None:
        hit &= errors.trans_error < thresholds.trans
    return np.asarray(ok, bool) & hit


def summarize(T_gt: np.ndarray, T_est: np.ndarray | None = None, *,
              valid: np.ndarray | None = None, raised: np.ndarray | None = None,
              thresholds: RecallThresholds = SEVEN_SCENES_RECALL) -> dict[str, Any]:
    """Table figures of one method over K pairs.

    Args:
        T_gt: (K, 4, 4) ground-truth ``T_target_source``.
        T_est: (K, 4, 4) estimates; rows of pairs that raised are ignored (identity is used).
        valid: (K,) bool, the method's own validity flag (default all True).
        raised: (K,) bool, the method raised on that pair (default all False).
        thresholds: recall thresholds.

    Returns:
        dict with ``rmse_r, rmse_t, mae_r, mae_t`` (Euler xyz deg / translation units),
        ``error_r, error_t`` (isotropic means), ``median_error_r, median_error_t``, ``recall``,
        ``n_pairs, n_success, n_invalid, n_exception`` and the threshold description.
    """
    T_gt = _as_transforms(T_gt).reshape(-1, 4, 4)
    k = T_gt.shape[0]
    if k == 0:
        raise ValueError("no pairs to summarize")
    raised = np.zeros(k, bool) if raised is None else np.asarray(raised, bool).reshape(k)
    valid = np.ones(k, bool) if valid is None else np.asarray(valid, bool).reshape(k)
    T_est = np.tile(np.eye(4), (k, 1, 1)) if T_est is None else _as_transforms(T_est).reshape(k, 4, 4).copy()
    T_est[raised] = np.eye(4)
    err = pair_errors(T_gt, T_est)
    ok = ~raised & valid
    success = success_mask(err, ok, thresholds)
    return {
        "rmse_r": float(np.sqrt(np.mean(err.euler_diff_deg ** 2))),
        "rmse_t": float(np.sqrt(np.mean(err.trans_diff ** 2))),
        "mae_r": float(np.mean(np.abs(err.euler_diff_deg))),
        "mae_t": float(np.mean(np.abs(err.trans_diff))),
        "error_r": float(np.mean(err.rot_error_deg)),
        "error_t": float(np.mean(err.trans_error)),
        "median_error_r": float(np.median(err.rot_error_deg)),
        "median_error_t": float(np.median(err.trans_error)),
        "recall": float(np.mean(success)),
        "n_pairs": int(k),
        "n_success": int(success.sum()),
        "n_invalid": int((~raised & ~valid).sum()),
        "n_exception": int(raised.sum()),
        "recall_definition": thresholds.describe(),
    }
