"""Two halves side by side (cegc_ros/parallel.py): the same answers and errors as in turn.

Every stage that uses :func:`both` must give what it gives one half after the other (the bound
stage's clouds and counts). The sequential path is forced by reporting one core (``parallel.cores``), the side-by-side one by
reporting two, whatever the machine has.
"""

from __future__ import annotations

import os
import threading
import time

import numpy as np
import pytest

from cegc_ros import bounding, parallel
from cegc_ros.bounding import bound_pair
from cegc_ros.config import PreprocessConfig
from cegc_ros.data.corruption import add_flying_pixels
from test_input_hygiene import _room


@pytest.fixture
def two_cores(monkeypatch):
    monkeypatch.setattr(parallel, "cores", lambda: 2)


def _one_core(monkeypatch):
    monkeypatch.setattr(parallel, "cores", lambda: 1)


def test_both_runs_the_second_half_on_another_thread_and_keeps_the_order(two_cores):
    caller = threading.get_ident()
    a, b = parallel.both(lambda x: (x, threading.get_ident()), "first", "second")
    assert a == ("first", caller)
    assert b[0] == "second" and b[1] != caller


def test_one_core_or_small_work_runs_both_halves_in_turn_on_the_calling_thread(monkeypatch):
    caller = threading.get_ident()
    monkeypatch.setattr(parallel, "cores", lambda: 2)
    assert parallel.both(lambda x: threading.get_ident(), 1, 2, side_by_side=False) == (caller, caller)
    _one_core(monkeypatch)
    assert parallel.both(lambda x: threading.get_ident(), 1, 2) == (caller, caller)


def test_the_first_halfs_error_wins_after_the_second_half_has_finished(two_cores):
    finished = threading.Event()

    def half(which: str) -> None:
        if which == "second":
            time.sleep(0.05)
            finished.set()
            raise KeyError("second")
        raise ValueError("source has 3 usable points")

    with pytest.raises(ValueError, match="source has 3 usable points"):
        parallel.both(half, "first", "second")
    assert finished.is_set()


def test_the_second_halfs_error_is_raised_when_the_first_succeeds(two_cores):
    def half(which: str) -> str:
        if which == "second":
            raise ValueError("target has 3 usable points")
        return which

    with pytest.raises(ValueError, match="target has 3 usable points"):
        parallel.both(half, "first", "second")


def test_nested_halves_run_in_turn_and_kdtree_queries_stay_on_one_thread(two_cores):
    def outer(x: int) -> tuple[int, tuple[int, int], int]:
        inner = parallel.both(lambda y: threading.get_ident(), 0, 1)
        return threading.get_ident(), inner, parallel.query_workers(10 ** 6)

    (t0, inner0, w0), (t1, inner1, w1) = parallel.both(outer, 0, 1)
    assert inner0 == (t0, t0) and inner1 == (t1, t1)          # nested: on the half's own thread
    assert w0 == w1 == 1
    assert parallel.query_workers(10 ** 6) == -1                # outside a half: every core
    assert parallel.query_workers(parallel.PARALLEL_QUERY_POINTS) == 1


def _halves_in_a_forked_child(queue) -> None:
    queue.put(parallel.both(lambda x: (x, threading.get_ident()), 1, 2))


@pytest.mark.skipif(not hasattr(os, "fork"), reason="no fork on this platform")
def test_a_forked_child_gets_its_own_worker_instead_of_the_parents(two_cores):
    import multiprocessing
    parallel.both(lambda x: x, 0, 1)                          # the parent's worker exists
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_halves_in_a_forked_child, args=(queue,))
    child.start()
    child.join(timeout=30)
    alive = child.is_alive()
    if alive:
        child.kill()
    assert not alive, "both() in a forked child waited for the parent's worker thread"
    (a, caller), (b, worker) = queue.get(timeout=10)
    assert (a, b) == (1, 2) and caller != worker


def _room_pair(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """test_input_hygiene's room: with 2% flying pixels as the source (the stray check runs), 80%
    of its points moved by a known shift as the target."""
    room = _room(n, seed)
    source = add_flying_pixels(room, 0.02, np.random.default_rng(seed + 1))
    keep = np.random.default_rng(seed + 2).permutation(len(room))[: int(0.8 * len(room))]
    return source, room[keep] + [0.3, 0.1, 0.0]


@pytest.mark.parametrize("settings", [{}, {"max_points": 3000},                  # coarser grids
                                      {"max_points": 3000, "voxel_ratio": 0.0}])  # seeded thinning
def test_bound_pair_gives_the_same_clouds_and_counts_side_by_side(monkeypatch, settings):
    cfg = PreprocessConfig(**settings)
    max_points = cfg.max_points
    source, target = _room_pair(70000, 3)
    assert bounding.SIDE_BY_SIDE_POINTS[0] <= min(len(source), len(target))
    threads = []
    survey = bounding._survey
    monkeypatch.setattr(bounding, "_survey", lambda *a: threads.append(threading.get_ident()) or survey(*a))
    _one_core(monkeypatch)
    turn = bound_pair(source, target, cfg, 16)
    assert len(set(threads)) == 1
    monkeypatch.setattr(parallel, "cores", lambda: 2)
    threads.clear()
    side = bound_pair(source, target, cfg, 16)
    assert len(set(threads)) == 2                            # the target's half on the worker
    assert turn.dropped[0].isolated > 0                      # the stray check ran on the source
    assert len(turn.source) <= max_points and len(turn.target) <= max_points
    np.testing.assert_array_equal(side.source, turn.source)
    np.testing.assert_array_equal(side.target, turn.target)
    assert side.voxel == turn.voxel and side.input_points == turn.input_points
    assert side.dropped == turn.dropped


def test_small_and_huge_clouds_are_bounded_in_turn(monkeypatch, two_cores):
    source, target = _room_pair(20000, 4)
    threads = []
    survey = bounding._survey
    monkeypatch.setattr(bounding, "_survey", lambda *a: threads.append(threading.get_ident()) or survey(*a))
    bound_pair(source, target, PreprocessConfig(), 16)
    assert threads == [threading.get_ident()] * 2
    threads.clear()
    monkeypatch.setattr(bounding, "SIDE_BY_SIDE_POINTS", (1000, len(target) - 1))   # the target is "huge"
    bound_pair(source, target, PreprocessConfig(), 16)
    assert threads == [threading.get_ident()] * 2
    threads.clear()
    monkeypatch.setattr(bounding, "SIDE_BY_SIDE_POINTS", (1000, len(source)))
    bound_pair(source, target, PreprocessConfig(), 16)
    assert len(set(threads)) == 2


def test_bound_pair_names_the_source_first_when_both_clouds_are_unusable(two_cores):
    bad = np.full((100, 3), np.nan)
    with pytest.raises(ValueError, match=r"^source has 0 usable points"):
        bound_pair(bad, bad, PreprocessConfig(), 16)
    with pytest.raises(ValueError, match=r"^target has 0 usable points"):
        bound_pair(_room_pair(5000, 0)[0], bad, PreprocessConfig(), 16)


def test_the_landing_search_gives_the_same_answers_side_by_side(monkeypatch):
    """refine._nearest (the verification's landing search) splits its queries between the two
    cores from SIDE_BY_SIDE_QUERIES on: the same landed flags and target indices as in turn, on
    poses of which some land and some do not, with the halves' split inside one pose."""
    from scipy.spatial.transform import Rotation
    from cegc_ros import refine
    rng = np.random.default_rng(5)
    target = rng.uniform(-1, 1, (512, 3))
    source = target[rng.permutation(512)] + rng.normal(0, 0.01, (512, 3))
    R = Rotation.random(41, random_state=6).as_matrix()
    R[:20] = np.eye(3)
    t = rng.normal(0, 0.02, (41, 3))
    t[:20] *= 0.1                                                       # near the identity: these land
    _one_core(monkeypatch)
    near_turn, j_turn = refine._nearest(R, t, source, target, 0.03)
    monkeypatch.setattr(parallel, "cores", lambda: 2)
    threads = []
    search = parallel.both
    monkeypatch.setattr(parallel, "both", lambda fn, a, b, side: threads.append(side) or search(fn, a, b, side))
    near_side, j_side = refine._nearest(R, t, source, target, 0.03)
    assert threads == [True]                                           # 41 x 512 >= SIDE_BY_SIDE_QUERIES
    assert np.array_equal(near_side, near_turn) and np.array_equal(j_side[near_side], j_turn[near_turn])
    assert near_turn[:20].mean() > 0.9 and near_turn[20:].mean() < 0.5  # some land, some do not
    refine._nearest(R[:2], t[:2], source, target, 0.03)
    assert threads == [True, False]                                    # 2 poses: in turn
