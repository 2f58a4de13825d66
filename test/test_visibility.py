"""Free space (cegc_ros/visibility.py) and its use in the estimator's verification."""

from __future__ import annotations

import numpy as np

from cegc_ros import estimator, visibility
from cegc_ros.metrics import rotation_error_deg


def _rz(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


def test_points_in_front_of_a_seen_wall_violate_and_others_do_not():
    rng = np.random.default_rng(0)
    wall = np.c_[np.full(4000, 3.0), rng.uniform(-2, 2, 4000), rng.uniform(-1, 1, 4000)]
    image = visibility.RangeImage.of(wall)
    probe = np.c_[np.zeros(500), rng.uniform(-1.2, 1.2, 500), rng.uniform(-0.5, 0.5, 500)]   # inside its view
    at = lambda x: probe + [x, 0.0, 0.0]                              # noqa: E731
    assert image.violations(at(2.0)) == 1.0                            # a metre in front: seen through
    assert image.violations(at(2.95)) == 0.0                           # on the surface, within the margin
    assert image.violations(at(4.0)) == 0.0                            # behind it: hidden, not free
    assert image.violations(-at(2.0)) == 0.0                           # a direction never seen
    # batched over poses: (H, N, 3) -> (H,)
    both = image.violations(np.stack([at(2.0), at(4.0)]))
    assert both.shape == (2,) and both.tolist() == [1.0, 0.0]


def test_cells_and_violations_equal_numpys_angles(monkeypatch):
    """The angles come from torch's vectorised kernels (speed); the cells and the violations are
    those of numpy's arctan2 / arcsin, on a room seen from its sensor and 40 poses of it, and the
    angles agree to 1 ulp. Reversed and read-only inputs work as numpy's did."""
    rng = np.random.default_rng(3)
    pts = _room(rng, 6000) - [0.2, 0.1, 1.2]
    other = _room(rng, 6000) - [0.6, -0.3, 1.2]
    x, y, z = pts.T
    r = np.sqrt(x * x + y * y + z * z)
    s = np.clip(z / r, -1.0, 1.0)
    az, el = visibility._azimuth_elevation(x, y, s)
    assert np.allclose(az, np.arctan2(y, x), rtol=3e-16, atol=1e-300)
    assert np.allclose(el, np.arcsin(s), rtol=3e-16, atol=1e-300)
    b = np.radians(visibility.BIN_DEG)
    rows = int(np.ceil(np.pi / b)) + 1
    key, _ = visibility._cells(x, y, z, b)
    expected = (np.floor((np.arctan2(y, x) + np.pi) / b).astype(np.int64) * rows
                + np.floor((np.arcsin(s) + np.pi / 2) / b).astype(np.int64))
    assert np.array_equal(key, expected)
    frozen = pts[::-1].copy()[::-1]                                    # a reversed view ...
    frozen.flags.writeable = False                                     # ... of read-only memory
    assert np.array_equal(visibility.RangeImage.of(frozen).nearest, visibility.RangeImage.of(pts).nearest)
    R = np.stack([_rz(np.degrees(a)) for a in rng.uniform(-0.3, 0.3, 40)])
    t = rng.normal(0, 0.3, (40, 3))
    fast = visibility.FreeSpace(pts, other).violations(R, t)
    monkeypatch.setattr(visibility, "_azimuth_elevation", lambda x, y, s: (np.arctan2(y, x), np.arcsin(s)))
    reference = visibility.FreeSpace(pts, other).violations(R, t)
    assert np.array_equal(fast, reference) and fast.max() > 0.05      # some poses do violate


def _room(rng: np.random.Generator, n: int) -> np.ndarray:
    """World points: a floor z = 0 over x in [-1, 3], y in [-3, 3] and a wall at x = 3."""
    k = n // 2
    floor = np.c_[rng.uniform(-1, 3, k), rng.uniform(-3, 3, k), np.zeros(k)]
    wall = np.c_[np.full(n - k, 3.0), rng.uniform(-3, 3, n - k), rng.uniform(0, 2, n - k)]
    return np.r_[floor, wall]


def test_a_pose_that_lays_floor_on_floor_is_caught_by_free_space():
    """Two sensors in a room see a floor and a wall. 200 confident correspondences agree with a
    wrong pose that slides the floor 1 m along itself (the wall then stands a metre in front of
    the other sensor's wall), 60 weaker ones with the right pose, 800 are random. The count and
    the fitness prefer the slide; its free-space violations give it away."""
    rng = np.random.default_rng(1)
    p_s, p_t, R_t = np.array([0.0, 0.0, 1.2]), np.array([0.5, 0.5, 1.2]), _rz(20.0)
    src = _room(rng, 4000) - p_s                                       # source frame = world axes
    tgt = (_room(rng, 4000) - p_t) @ R_t                               # target frame: yawed 20 deg
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R_t.T, R_t.T @ (p_s - p_t)                   # T_target_source
    slide = np.eye(4)
    slide[:3, 3] = [-1.0, 0.0, 0.0]
    T_wrong = T @ slide

    def moved(M: np.ndarray, p: np.ndarray) -> np.ndarray:
        return p @ M[:3, :3].T + M[:3, 3]

    wall, floor = np.flatnonzero(src[:, 2] > -1.15), np.flatnonzero(np.abs(src[:, 2] + 1.2) < 1e-9)
    right = rng.choice(wall, 60, replace=False)
    wrong = rng.choice(floor[np.abs(src[floor, 0]) < 1.5], 200, replace=False)
    noise = rng.choice(len(src), 800, replace=False)
    cs = np.r_[src[right], src[wrong], src[noise]]
    ct = np.r_[moved(T, src[right]), moved(T_wrong, src[wrong]), tgt[rng.choice(len(tgt), 800)]]
    w = np.r_[np.full(60, 0.4), np.full(200, 0.6), rng.uniform(0, 0.3, 800)]
    thr = 0.2

    def solve(explore: int, free: float, sure: float = 1.01) -> estimator.Estimate:
        cfg = estimator.CompatibilityConfig(verify=50, explore_seeds=explore, free_space=free,
                                            sure_fitness=sure)
        return estimator.estimate_compatibility(cs, ct, w, thr, cfg, (src, tgt), (src, tgt))

    def error(e: estimator.Estimate, M: np.ndarray) -> tuple[float, float]:
        return float(rotation_error_deg(M[:3, :3], e.R)), float(np.linalg.norm(M[:3, 3] - e.t))

    plain = solve(0, 0.0)
    assert error(plain, T_wrong)[1] < 0.05                             # the slide wins on count x fitness
    assert error(solve(200, 0.0), T_wrong)[1] < 0.05                   # more seeds alone: still the slide
    checked = solve(200, 10.0)
    rot, trans = error(checked, T)
    assert rot < 1.0 and trans < 0.05
    # the violations behind it: the slide puts the part of the source's wall that the target
    # sensor sees past (a fifth of the points) in front of the target's wall
    v = visibility.free_space_violations(np.stack([T[:3, :3], T_wrong[:3, :3]]),
                                         np.stack([T[:3, 3], T_wrong[:3, 3]]), src, tgt)
    assert v[0] < 0.02 and v[1] > 0.15
    # the second pass runs only below sure_fitness: the slide's fitness is ~0.44
    assert error(solve(200, 10.0, sure=0.3), T_wrong)[1] < 0.05
    assert error(solve(200, 10.0, sure=0.85), T)[1] < 0.05
    # the same answer twice: the exploring seeds are drawn from a fixed stream
    again = solve(200, 10.0)
    assert np.array_equal(again.R, checked.R) and np.array_equal(again.t, checked.t)
