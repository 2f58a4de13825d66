"""Approximate-time pairing: exact pairs, slop boundary, out-of-order stamps, bounded buffers."""

from __future__ import annotations

import pytest

from cegc_ros.pairing import ApproximatePairer

MS = 1_000_000  # ns


def test_same_stamp_pairs_immediately_either_order():
    p: ApproximatePairer[str] = ApproximatePairer(slop_s=0.05, buffer_size=4)
    assert p.add("source", 1000 * MS, "s0").pair is None
    r = p.add("target", 1000 * MS, "t0")
    assert r.pair is not None and (r.pair.source.msg, r.pair.target.msg) == ("s0", "t0")
    assert r.pair.dt_ns == 0
    r = p.add("target", 1500 * MS, "t1")
    assert r.pair is None
    r = p.add("source", 1500 * MS, "s1")
    assert (r.pair.source.msg, r.pair.target.msg) == ("s1", "t1")
    assert p.stats.paired == 2 and p.stats.received == {"source": 2, "target": 2}
    assert p.pending("source") == [] and p.pending("target") == []


def test_slop_boundary_is_inclusive_and_outside_waits():
    p: ApproximatePairer[str] = ApproximatePairer(slop_s=0.05, buffer_size=4)
    p.add("source", 0, "s0")
    assert p.add("target", 50 * MS, "t_in").pair.dt_ns == 50 * MS   # exactly the slop: paired
    p.add("source", 1000 * MS, "s1")
    assert p.add("target", 1051 * MS, "t_out").pair is None          # 51 ms > 50 ms
    assert [s.msg for s in p.pending("source")] == ["s1"]
    assert [s.msg for s in p.pending("target")] == ["t_out"]
    # Raising the slop at run time applies to the next message.
    p.slop_s = 0.1
    assert p.add("source", 1100 * MS, "s2").pair.target.msg == "t_out"  # |1100-1051| = 49 ms
    assert [s.msg for s in p.pending("source")] == ["s1"]


def test_closest_partner_wins_and_ties_go_to_older():
    p: ApproximatePairer[str] = ApproximatePairer(slop_s=0.1, buffer_size=8)
    for t, name in [(900, "a"), (960, "b"), (1040, "c"), (1100, "d")]:
        p.add("target", t * MS, name)
    r = p.add("source", 1010 * MS, "s")   # b is 50 ms away, c 30 ms: c
    assert r.pair.target.msg == "c" and r.pair.dt_ns == 30 * MS
    r = p.add("source", 1030 * MS, "s2")  # b 70 ms, d 70 ms: tie -> older (b)
    assert r.pair.target.msg == "b"
    assert [s.msg for s in p.pending("target")] == ["a", "d"]


def test_out_of_order_stamps_pair_by_stamp_not_arrival():
    p: ApproximatePairer[str] = ApproximatePairer(slop_s=0.01, buffer_size=8)
    # Sources arrive 3, 1, 2; targets arrive 2, 3, 1 (stamps in seconds).
    for t, name in [(3, "s3"), (1, "s1"), (2, "s2")]:
        assert p.add("source", t * 1000 * MS, name).pair is None
    assert [s.stamp_ns for s in p.pending("source")] == [1000 * MS, 2000 * MS, 3000 * MS]
    got = []
    for t, name in [(2, "t2"), (3, "t3"), (1, "t1")]:
        pair = p.add("target", t * 1000 * MS + 5 * MS, name).pair
        got.append((pair.source.msg, pair.target.msg, pair.dt_ns))
    assert got == [("s2", "t2", 5 * MS), ("s3", "t3", 5 * MS), ("s1", "t1", 5 * MS)]
    assert p.stats.paired == 3 and p.stats.dropped == {"source": 0, "target": 0}


def test_full_buffer_drops_oldest_stamp_and_reports_it():
    p: ApproximatePairer[int] = ApproximatePairer(slop_s=0.0, buffer_size=3)
    for k in range(3):
        assert p.add("source", k * 100 * MS, k).unpaired == []
    r = p.add("source", 50 * MS, 99)        # arrives late, lands second-oldest
    assert [s.msg for s in r.unpaired] == [0] and r.unpaired[0].side == "source"
    r = p.add("source", 1 * MS, 98)         # older than everything buffered: dropped itself
    assert [s.msg for s in r.unpaired] == [98]
    assert [s.msg for s in p.pending("source")] == [99, 1, 2]
    assert p.stats.dropped == {"source": 2, "target": 0}
    # Shrinking the buffer drops on the next add.
    p.buffer_size = 1
    r = p.add("target", 5000 * MS, -1)
    assert [s.msg for s in r.unpaired] == [99, 1]
    assert p.stats.dropped == {"source": 4, "target": 0}
    assert [s.msg for s in p.flush()] == [2, -1]
    assert p.pending("source") == [] and p.pending("target") == []


def test_burst_on_one_stream_keeps_memory_bounded():
    p: ApproximatePairer[int] = ApproximatePairer(slop_s=0.05, buffer_size=10)
    dropped = sum(len(p.add("source", k * MS * 1000, k).unpaired) for k in range(1000))
    assert dropped == 990 and len(p.pending("source")) == 10
    # The ten newest are still pairable.
    assert p.add("target", 999_000 * MS, 0).pair.source.msg == 999


def test_invalid_settings_raise():
    with pytest.raises(ValueError, match="slop"):
        ApproximatePairer(slop_s=-0.1, buffer_size=1)
    with pytest.raises(ValueError, match="buffer size"):
        ApproximatePairer(slop_s=0.1, buffer_size=0)
    p: ApproximatePairer[int] = ApproximatePairer(slop_s=0.1, buffer_size=1)
    with pytest.raises(ValueError, match="side"):
        p.add("left", 0, 0)  # type: ignore[arg-type]
