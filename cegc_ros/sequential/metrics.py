"""Trajectory errors of an odometry against ground truth (numpy only).

Both trajectories are ``(K, 4, 4)`` poses ``T_odom_cloud`` in the first cloud's frame (the
ground truth made relative with ``inv(T_world_0) @ T_world_k``). A method that gave no pose for
a cloud has NaN there; every metric skips those frames and says how many it used.

- ATE (absolute trajectory error): RMS of the position errors, (a) from the first frame (both
  start at the identity; no fitting, so early drift counts in full: the number an odometry user
  sees) and (b) after the rigid (SE(3), no scale) alignment of the estimated positions onto the
  ground truth that minimises it (Horn / Umeyama; the TUM benchmark's ATE).
- RPE (relative pose error, KITTI style): for every start frame i and segment length L, the
  first frame j whose ground-truth path from i is at least L long; the error of the estimated
  motion i -> j against the true one, as translation % of L and rotation deg per metre.
- Per-step error: the same for consecutive frames (j = i + 1), in metres and degrees, for
  sequences whose path length is too short for per-metre figures (an object on a turntable).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def _angle_deg(R: np.ndarray) -> np.ndarray:
    """Rotation angles (deg) of (..., 3, 3) rotations."""
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def _valid(T: np.ndarray) -> np.ndarray:
    return np.isfinite(T).all(axis=(1, 2))


def align_se3(P_est: np.ndarray, P_gt: np.ndarray) -> np.ndarray:
    """(4, 4) rigid transform minimising sum |T p_est - p_gt|^2 over (K, 3) positions (K >= 3)."""
    mu_e, mu_g = P_est.mean(0), P_gt.mean(0)
    U, _, Vt = np.linalg.svd((P_gt - mu_g).T @ (P_est - mu_e))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    T = np.eye(4)
    T[:3, :3] = U @ D @ Vt
    T[:3, 3] = mu_g - T[:3, :3] @ mu_e
    return T


def ate(T_gt: np.ndarray, T_est: np.ndarray) -> dict[str, float]:
    """Absolute trajectory error: rmse_first / max_first (m, from the first frame),
    rmse_aligned (m, after :func:`align_se3`), rot_first (mean rotation error, deg),
    frames (poses used) and coverage (their share of the frames)."""
    ok = _valid(T_est)
    n = int(ok.sum())
    out = {"frames": n, "coverage": n / max(len(T_gt), 1)}
    if n == 0:
        return out | {"rmse_first": float("nan"), "max_first": float("nan"),
                      "rmse_aligned": float("nan"), "rot_first": float("nan")}
    G, E = T_gt[ok], T_est[ok]
    err = np.linalg.norm(E[:, :3, 3] - G[:, :3, 3], axis=1)
    out["rmse_first"] = float(np.sqrt((err ** 2).mean()))
    out["max_first"] = float(err.max())
    out["rot_first"] = float(_angle_deg(np.swapaxes(G[:, :3, :3], 1, 2) @ E[:, :3, :3]).mean())
    if n >= 3:
        A = align_se3(E[:, :3, 3], G[:, :3, 3])
        moved = E[:, :3, 3] @ A[:3, :3].T + A[:3, 3]
        out["rmse_aligned"] = float(np.sqrt((np.linalg.norm(moved - G[:, :3, 3], axis=1) ** 2)
                                            .mean()))
    else:
        out["rmse_aligned"] = out["rmse_first"]
    return out


def _relative_errors(T_gt: np.ndarray, T_est: np.ndarray, i: np.ndarray, j: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Translation (m) and rotation (deg) errors of the motions i -> j."""
    D_gt = np.linalg.inv(T_gt[i]) @ T_gt[j]
    D_est = np.linalg.inv(T_est[i]) @ T_est[j]
    E = np.linalg.inv(D_gt) @ D_est
    return np.linalg.norm(E[:, :3, 3], axis=1), _angle_deg(E[:, :3, :3])


def rpe(T_gt: np.ndarray, T_est: np.ndarray, lengths: Sequence[float]) -> dict[str, dict]:
    """Relative pose error per segment length (metres of ground-truth path).

    Returns {f"{L:g}": {"trans_pct", "rot_deg_per_m", "segments"}}; NaN and 0 segments when
    the sequence is shorter than L or no segment has both ends estimated.
    """
    steps = np.linalg.norm(np.diff(T_gt[:, :3, 3], axis=0), axis=1)
    dist = np.r_[0.0, np.cumsum(steps)]                                  # (K,)
    ok = _valid(T_est)
    out: dict[str, dict] = {}
    for L in lengths:
        i = np.arange(len(T_gt))
        j = np.searchsorted(dist, dist + L - 1e-12)                      # first j with path >= L
        keep = (j < len(T_gt))
        i, j = i[keep], j[keep]
        keep = ok[i] & ok[j]
        i, j = i[keep], j[keep]
        if len(i) == 0:
            out[f"{L:g}"] = {"trans_pct": float("nan"), "rot_deg_per_m": float("nan"),
                             "segments": 0}
            continue
        t, r = _relative_errors(T_gt, T_est, i, j)
        seg = dist[j] - dist[i]
        out[f"{L:g}"] = {"trans_pct": float(100.0 * (t / seg).mean()),
                         "rot_deg_per_m": float((r / seg).mean()), "segments": len(i)}
    return out


def step_errors(T_gt: np.ndarray, T_est: np.ndarray) -> dict[str, float]:
    """Errors of the motion between consecutive frames with both poses: mean and max
    translation (m) and rotation (deg), and how many steps were scored."""
    ok = _valid(T_est)
    i = np.flatnonzero(ok[:-1] & ok[1:])
    if len(i) == 0:
        return {"trans_mean": float("nan"), "trans_max": float("nan"),
                "rot_mean": float("nan"), "rot_max": float("nan"), "steps": 0}
    t, r = _relative_errors(T_gt, T_est, i, i + 1)
    return {"trans_mean": float(t.mean()), "trans_max": float(t.max()),
            "rot_mean": float(r.mean()), "rot_max": float(r.max()), "steps": len(i)}


def path_length(T_gt: np.ndarray) -> float:
    """Length (m) of the ground-truth path."""
    return float(np.linalg.norm(np.diff(T_gt[:, :3, 3], axis=0), axis=1).sum())
