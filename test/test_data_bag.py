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
