"""Pair bags (cegc_ros.data.bag) and the cegc-make-bag CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cegc_ros.data import bag as B
from cegc_ros.data import protocols as P
from cegc_ros.tools import make_bag


@pytest.fixture(scope="module")
def pairs() -> list[P.Pair]:
    return P.make_pairs("modelnet", "test", 4, seed=3)


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_round_trip(tmp_path, pairs, storage):
    out = tmp_path / "bag"
    assert B.write_pairs(out, pairs, storage=storage, protocol="modelnet", seed=3) == 4
    suffix = {"sqlite3": ".db3", "mcap": ".mcap"}[storage]
    assert [p.suffix for p in out.iterdir() if p.name != "metadata.yaml"] == [suffix]
    back = list(B.read_pairs(out))
    assert len(back) == 4
    for k, (a, b) in enumerate(zip(pairs, back)):
        assert np.array_equal(a.source, b.source) and np.array_equal(a.target, b.target)
        assert b.source.dtype == np.float32
        np.testing.assert_allclose(b.T_target_source, a.T_target_source, atol=1e-12)
        assert b.stamp_ns == B.START_NS + k * 500_000_000
        assert b.info["protocol"] == "modelnet" and b.info["seed"] == 3 and b.info["index"] == k
        assert b.info["overlap"] == pytest.approx(a.info["overlap"])


def test_messages_share_stamp_and_frames(tmp_path, pairs):
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    out = tmp_path / "bag"
    B.write_pairs(out, pairs[:2], storage="mcap")
    ts = get_typestore(Stores.ROS2_JAZZY)
    seen: dict[str, list[tuple[int, str]]] = {}
    with Reader(out) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        for conn, t, raw in reader.messages():
            msg = ts.deserialize_cdr(raw, conn.msgtype)
            if conn.topic == B.TOPIC_INFO:
                assert json.loads(msg.data)["protocol"] == "modelnet"
                seen.setdefault(conn.topic, []).append((t, ""))
                continue
            stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            assert stamp == t
            seen.setdefault(conn.topic, []).append((stamp, msg.header.frame_id))
    assert types == {"/cegc/source": "sensor_msgs/msg/PointCloud2",
                     "/cegc/target": "sensor_msgs/msg/PointCloud2",
                     "/cegc/ground_truth": "geometry_msgs/msg/PoseStamped",
                     "/cegc/pair_info": "std_msgs/msg/String"}
    s0, s1 = B.START_NS, B.START_NS + 500_000_000
    assert seen["/cegc/source"] == [(s0, "cegc_source"), (s1, "cegc_source")]
    assert seen["/cegc/target"] == [(s0, "cegc_target"), (s1, "cegc_target")]
    assert seen["/cegc/ground_truth"] == [(s0, "cegc_target"), (s1, "cegc_target")]
    assert [t for t, _ in seen["/cegc/pair_info"]] == [s0, s1]


def test_bag_without_ground_truth_yields_none(tmp_path, pairs):
    bare = [B.BagPair(p.source, p.target, None, 0, {}) for p in pairs[:3]]
    out = tmp_path / "bag"
    B.write_pairs(out, bare)
    back = list(B.read_pairs(out))
    assert len(back) == 3 and all(p.T_target_source is None for p in back)
    assert np.array_equal(back[2].target, pairs[2].target)


@pytest.mark.parametrize("storage,ext", [("sqlite3", "db3"), ("mcap", "mcap")])
def test_truncated_bag_raises_bag_error(tmp_path, pairs, storage, ext):
    out = tmp_path / "bag"
    B.write_pairs(out, pairs, storage=storage)
    data = (out / f"bag.{ext}").read_bytes()
    (out / f"bag.{ext}").write_bytes(data[: len(data) // 2])
    with pytest.raises(B.BagError, match="bag"):
        list(B.read_pairs(out))


def test_missing_and_garbage_bags_raise_bag_error(tmp_path, pairs):
    with pytest.raises(B.BagError, match="does not exist"):
        list(B.read_pairs(tmp_path / "nothing"))
    out = tmp_path / "bag"
    B.write_pairs(out, pairs[:1])
    (out / "bag.db3").write_bytes(b"not a database" * 100)
    with pytest.raises(B.BagError, match="cannot open") as info:
        list(B.read_pairs(out))
    assert info.value.__cause__ is not None                     # the rosbags error is chained


def test_foreign_bag_raises_bag_error(tmp_path):
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    out = tmp_path / "chatter"
    with Writer(out, version=9) as w:
        c = w.add_connection("/chatter", "std_msgs/msg/String", typestore=ts)
        w.write(c, 1, ts.serialize_cdr(ts.types["std_msgs/msg/String"](data="hi"),
                                       "std_msgs/msg/String"))
    with pytest.raises(B.BagError, match=r"not a pair bag.*/cegc/source"):
        list(B.read_pairs(out))
    out2 = tmp_path / "wrong_type"
    with Writer(out2, version=9) as w:
        for topic in (B.TOPIC_SOURCE, B.TOPIC_TARGET):
            c = w.add_connection(topic, "std_msgs/msg/String", typestore=ts)
    with pytest.raises(B.BagError, match="expected sensor_msgs/msg/PointCloud2"):
        list(B.read_pairs(out2))


def test_write_refuses_existing_path(tmp_path, pairs):
    with pytest.raises(B.BagError, match="exists"):
        B.write_pairs(tmp_path, pairs)
    with pytest.raises(B.BagError, match="storage"):
        B.write_pairs(tmp_path / "x", pairs, storage="rosbag1")


def test_pointcloud2_decoder_handles_padded_organised_clouds():
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    # 2 x 3 organised cloud, fields x y z at offsets 0 4 8 plus 4 bytes of padding (16 B),
    # one NaN point; rows come out in row-major order.
    rec = np.zeros((2, 3), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("pad", "<f4")])
    rec["x"] = np.arange(6).reshape(2, 3)
    rec["y"], rec["z"] = 1.0, 2.0
    rec["x"][1, 1] = np.nan
    PF = ts.types["sensor_msgs/msg/PointField"]
    msg = ts.types["sensor_msgs/msg/PointCloud2"](
        header=B._header(ts, 0, "f"), height=2, width=3,
        fields=[PF(name=n, offset=4 * k, datatype=7, count=1) for k, n in enumerate("xyz")],
        is_bigendian=False, point_step=16, row_step=48, data=rec.view(np.uint8).reshape(-1),
        is_dense=False)
    xyz = B.pointcloud2_to_xyz(msg)
    np.testing.assert_array_equal(xyz[:, 0], [0, 1, 2, 3, 5])
    assert np.all(xyz[:, 1] == 1.0) and np.all(xyz[:, 2] == 2.0)
    msg.data = msg.data[:40]
    with pytest.raises(B.BagError, match="bytes"):
        B.pointcloud2_to_xyz(msg)


def test_cli_writes_bag_and_rejects_bad_input(tmp_path, capsys):
    out = tmp_path / "cli"
    argv = ["--protocol", "modelnet", "--split", "test", "--pairs", "3", "--seed", "9",
            "--out", str(out), "--storage", "mcap", "--no-progress"]
    assert make_bag.main(argv) == 0
    back = list(B.read_pairs(out))
    assert [p.info["index"] for p in back] == [0, 1, 2]
    assert np.array_equal(back[1].source, P.make_pair("modelnet", "test", 1, 9).source)
    with pytest.raises(SystemExit) as exc:                     # out exists now
        make_bag.main(argv)
    assert exc.value.code == 2 and "exists already" in capsys.readouterr().err
    assert make_bag.main([*argv, "--overwrite"]) == 0          # the README's block, run twice
    assert [p.info["index"] for p in B.read_pairs(out)] == [0, 1, 2]
    deep = tmp_path / "fresh" / "bags" / "cli"                 # missing parents are created
    assert make_bag.main([*argv[:-4], str(deep), "--storage", "mcap", "--no-progress"]) == 0
    assert [p.info["index"] for p in B.read_pairs(deep)] == [0, 1, 2]
    (tmp_path / "a_file").write_text("x")                      # a parent that is a file is not
    with pytest.raises(SystemExit) as exc:
        make_bag.main([*argv[:-4], str(tmp_path / "a_file" / "cli"), "--storage", "mcap", "--no-progress"])
    assert exc.value.code == 2 and "is a file, not a directory" in capsys.readouterr().err
    keep = tmp_path / "not_a_bag"
    keep.mkdir()
    (keep / "notes.txt").write_text("mine")
    with pytest.raises(SystemExit) as exc:
        make_bag.main([*argv[:-4], str(keep), "--storage", "mcap", "--no-progress", "--overwrite"])
    assert exc.value.code == 2 and "is not a rosbag2 bag" in capsys.readouterr().err
    assert (keep / "notes.txt").read_text() == "mine"
    for bad in (["--pairs", "0"], ["--protocol", "kitti"], ["--seed", "-1"]):
        args = list(argv)
        args[args.index(bad[0]) + 1] = bad[1]
        args[args.index("--out") + 1] = str(tmp_path / "new")
        with pytest.raises(SystemExit) as exc:
            make_bag.main(args)
        assert exc.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err[-1].startswith("cegc-make-bag: error:")


def test_bag_with_fewer_messages_than_its_metadata_raises(tmp_path, pairs):
    import sqlite3

    out = tmp_path / "bag"
    B.write_pairs(out, pairs)
    with sqlite3.connect(out / "bag.db3") as db:               # a recording cut short
        db.execute("DELETE FROM messages WHERE timestamp = (SELECT MAX(timestamp) FROM messages)")
    with pytest.raises(B.BagError, match="truncated: metadata lists 16 messages, storage has 12"):
        list(B.read_pairs(out))


# --------------------------------------------------------------------------------------------
# Grouping messages by header stamp (shared by read_pairs and read_sequence)
# --------------------------------------------------------------------------------------------

def _raw_bag(path, types: dict[str, str], messages) -> None:
    """Write a bag by hand: ``messages`` is a list of (topic, log time, header stamp, payload)
    with payload an (N, 3) cloud, a (4, 4) pose or b"..." raw CDR bytes (a broken message)."""
    from rosbags.rosbag2 import Writer

    ts = B._typestore()
    with Writer(path, version=9) as w:
        conns = {t: w.add_connection(t, m, typestore=ts) for t, m in types.items()}
        for topic, logtime, stamp, payload in messages:
            if isinstance(payload, bytes):
                raw = payload
            else:
                header = B._header(ts, stamp, "f")
                msg = (B.xyz_to_pointcloud2(ts, payload, header) if payload.shape[1] == 3
                       else B.matrix_to_pose_stamped(ts, payload, header))
                raw = ts.serialize_cdr(msg, types[topic])
            w.write(conns[topic], logtime, raw)


def _consume(it) -> tuple[list, str]:
    """(items yielded before the iterator stopped, the BagError text or "")."""
    got = []
    try:
        for item in it:
            got.append(item)
    except B.BagError as err:
        return got, str(err)
    return got, ""


_PAIR_TYPES = {t: B._TYPES[t] for t in (B.TOPIC_SOURCE, B.TOPIC_TARGET, B.TOPIC_GT)}
_SEQ_TYPES = {t: B._SEQUENCE_TYPES[t] for t in (B.TOPIC_CLOUD, B.TOPIC_CLOUD_GT)}


def _pts(k: int) -> np.ndarray:
    return np.full((2, 3), float(k), np.float32)


def _pose(k: int) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = k
    return T


def test_pairs_are_grouped_by_stamp_in_completion_order(tmp_path):
    S, T, G = B.TOPIC_SOURCE, B.TOPIC_TARGET, B.TOPIC_GT
    out = tmp_path / "bag"
    _raw_bag(out, _PAIR_TYPES, [
        (S, 1, 100, _pts(1)), (T, 2, 100, _pts(2)),                  # 100: no ground truth
        (S, 3, 200, _pts(3)), (G, 4, 200, _pose(4)), (T, 5, 200, _pts(5)),
        (T, 6, 50, _pts(6)), (S, 7, 50, _pts(7)), (G, 8, 50, _pose(8)),   # stamp goes back
        (G, 9, 400, _pose(9)), (S, 10, 300, _pts(10)),               # 400 and 300 never complete
        (T, 11, 300, _pts(11))])
    got, err = _consume(B.read_pairs(out))
    # 100 is yielded (without ground truth) when 200 completes; 50 completes on its own; the
    # leftovers 300 and 400 come in stamp order at the end, and 400 has no clouds.
    assert [p.stamp_ns for p in got] == [100, 200, 50, 300]
    assert [None if p.T_target_source is None else p.T_target_source[0, 3] for p in got] == \
        [None, 4.0, 8.0, None]
    assert [(p.source[0, 0], p.target[0, 0]) for p in got] == [(1, 2), (3, 5), (7, 6), (10, 11)]
    assert err == (f"{out}: pair at stamp 400 lacks ['/cegc/source', '/cegc/target'] "
                   "(truncated bag?)")


def test_sequence_frames_are_grouped_by_stamp_in_completion_order(tmp_path):
    C, G = B.TOPIC_CLOUD, B.TOPIC_CLOUD_GT
    out = tmp_path / "seq"
    _raw_bag(out, _SEQ_TYPES, [
        (C, 1, 100, _pts(1)), (C, 2, 200, _pts(2)),                  # 100: no ground truth
        (G, 3, 200, _pose(3)), (G, 4, 50, _pose(4)), (C, 5, 50, _pts(5)),
        (C, 6, 300, _pts(6)), (G, 7, 250, _pose(7))])                # 250 never gets a cloud
    got, err = _consume(B.read_sequence(out))
    assert [(f.stamp_ns, f.cloud[0, 0]) for f in got] == [(100, 1), (200, 2), (50, 5)]
    assert [None if f.T_world_cloud is None else f.T_world_cloud[0, 3] for f in got] == \
        [None, 3.0, 4.0]
    assert err == f"{out}: ground truth at stamp 250 has no cloud (truncated bag?)"


def test_grouping_rejects_duplicate_stamps(tmp_path):
    S, T, C = B.TOPIC_SOURCE, B.TOPIC_TARGET, B.TOPIC_CLOUD
    out = tmp_path / "bag"
    _raw_bag(out, _PAIR_TYPES, [(S, 1, 100, _pts(1)), (S, 2, 100, _pts(2)),
                                (T, 3, 100, _pts(3))])
    got, err = _consume(B.read_pairs(out))
    assert got == [] and err == f"{out}: two /cegc/source messages with stamp 100"
    seq = tmp_path / "seq"
    _raw_bag(seq, _SEQ_TYPES, [(C, 1, 100, _pts(1)), (C, 2, 200, _pts(2)),
                               (C, 3, 200, _pts(3)), (B.TOPIC_CLOUD_GT, 4, 100, _pose(4))])
    got, err = _consume(B.read_sequence(seq))
    assert got == [] and err == f"{seq}: two /cegc/cloud messages with stamp 200"
    # Only a group still pending is checked: a stamp repeated after its group was yielded
    # starts a new group (here every cloud completes its group at once: no ground truth).
    again = tmp_path / "again"
    _raw_bag(again, {C: B._SEQUENCE_TYPES[C]}, [(C, 1, 100, _pts(1)), (C, 2, 200, _pts(2)),
                                                (C, 3, 200, _pts(3))])
    got, err = _consume(B.read_sequence(again))
    assert [(f.stamp_ns, f.cloud[0, 0]) for f in got] == [(100, 1), (200, 2), (200, 3)]
    assert err == ""


def test_grouping_counts_messages_seen_against_metadata(tmp_path, pairs):
    import sqlite3

    S, T, C = B.TOPIC_SOURCE, B.TOPIC_TARGET, B.TOPIC_CLOUD
    out = tmp_path / "bag"                                    # 3rd of 4 messages is not CDR
    _raw_bag(out, _PAIR_TYPES, [(S, 1, 100, _pts(1)), (T, 2, 100, _pts(2)),
                                (S, 3, 200, b"\x00\x01"), (T, 4, 200, _pts(4))])
    got, err = _consume(B.read_pairs(out))
    assert [p.stamp_ns for p in got] == [100]
    assert err.startswith(f"{out}: storage unreadable after 3 of 4 messages (truncated or "
                          "corrupted?): ")
    seq = tmp_path / "seq"
    _raw_bag(seq, _SEQ_TYPES, [(C, 1, 100, _pts(1)), (C, 2, 200, b"\x00\x01")])
    got, err = _consume(B.read_sequence(seq))
    assert [f.stamp_ns for f in got] == [100]
    assert err.startswith(f"{seq}: storage unreadable after 2 of 2 messages")
    cut = tmp_path / "cut"                                    # sequence_info is not counted
    B.write_sequence(cut, _three_frames())
    with sqlite3.connect(cut / "cut.db3") as db:
        db.execute("DELETE FROM messages WHERE timestamp = (SELECT MAX(timestamp) FROM messages)")
    got, err = _consume(B.read_sequence(cut))
    assert [f.stamp_ns for f in got] == [10, 20]              # read before the count is checked
    assert err == f"{cut} is truncated: metadata lists 6 messages, storage has 4"


def _three_frames():
    from cegc_ros.data import sequences as Q

    return Q.Sequence([_pts(k) for k in range(3)], np.stack([_pose(k) for k in range(3)]),
                      [10, 20, 30], "lidar", {"n": 3})
