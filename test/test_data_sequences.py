"""Sequences for sequential mode (cegc_ros.data.sequences) and sequence bags (cegc_ros.data.bag)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from cegc_ros.data import bag as B
from cegc_ros.data import sequences as Q


@pytest.fixture(scope="module")
def room_sequence() -> Q.Sequence:
    return Q.make_room_sequence(3, 6, frame_step=3, pixel_stride=8)


def _near_fraction(a: np.ndarray, b: np.ndarray, T_a_b: np.ndarray, dist: float) -> float:
    d, _ = cKDTree(a).query(b @ T_a_b[:3, :3].T + T_a_b[:3, 3])
    return float((d < dist).mean())


def test_room_sequence_clouds_agree_with_their_ground_truth(room_sequence):
    seq = room_sequence
    assert len(seq) == 6 and len(seq.poses) == 6
    assert np.all(np.diff(seq.stamps_ns) == 100_000_000)              # 30 fps, every 3rd frame
    rel = seq.relative_poses()
    np.testing.assert_allclose(rel[0], np.eye(4), atol=1e-12)
    for k in range(1, len(seq)):
        T = np.linalg.inv(rel[k - 1]) @ rel[k]
        aligned = _near_fraction(seq.clouds[k - 1], seq.clouds[k], T, 0.05)
        unaligned = _near_fraction(seq.clouds[k - 1], seq.clouds[k], np.eye(4) @ np.linalg.inv(T),
                                   0.05)
        assert aligned > 0.8 and aligned > unaligned + 0.1, (k, aligned, unaligned)
    assert all(c.dtype == np.float32 and c.shape[1] == 3 and len(c) > 1000 for c in seq.clouds)
    assert seq.info["trajectory"] == "robot" and seq.info["scene_seed"] == 3


def test_room_sequence_is_deterministic_and_prefix_stable(room_sequence):
    again = Q.make_room_sequence(3, 4, frame_step=3, pixel_stride=8)
    for a, b in zip(again.clouds, room_sequence.clouds):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(again.poses, room_sequence.poses[:4])


def test_robot_camera_moves_at_its_speed_and_stays_clear():
    room = Q.scenes.get_room(3)
    poses = Q.robot_trajectory(room, 90, fps=30.0, speed=0.4)
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    np.testing.assert_allclose(steps, 0.4 / 30.0, rtol=0.02)
    np.testing.assert_allclose(poses[:, 2, 3], 1.2)
    R = poses[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.tile(np.eye(3), (90, 1, 1)), atol=1e-9)
    import open3d as o3d
    clear = room.scene.compute_distance(o3d.core.Tensor(poses[:, :3, 3].astype(np.float32)))
    assert clear.numpy().min() >= 0.3 - 1e-3


def test_fused_clouds_and_bad_arguments():
    one = Q.make_room_sequence(5, 1, frames_per_cloud=1, pixel_stride=8, noise=False)
    three = Q.make_room_sequence(5, 1, frames_per_cloud=3, pixel_stride=8, noise=False)
    assert len(three.clouds[0]) > 2 * len(one.clouds[0])
    with pytest.raises(ValueError, match="trajectory"):
        Q.make_room_sequence(5, 2, trajectory="drone")
    with pytest.raises(ValueError, match="num_clouds"):
        Q.make_room_sequence(5, 0)


def test_subset_drops_frames_keeping_stamps_and_poses(room_sequence):
    sub = room_sequence.subset([0, 4, 5])
    assert list(sub.stamps_ns) == [room_sequence.stamps_ns[i] for i in (0, 4, 5)]
    np.testing.assert_array_equal(sub.poses[1], room_sequence.poses[4])
    assert sub.clouds[2] is room_sequence.clouds[5]


def _fake_bunny(root, T_by_scan: dict[str, np.ndarray], pairs: list[tuple[str, str]]) -> None:
    """A bunny folder: scans are one random object seen from T_by_scan (T_object_scan)."""
    rng = np.random.default_rng(0)
    obj = rng.normal(size=(500, 3)) * [0.05, 0.03, 0.04]
    (root / "scans").mkdir(parents=True)
    (root / "gt").mkdir()
    for name, T in T_by_scan.items():
        Ti = np.linalg.inv(T)
        np.save(root / "scans" / f"{name}.npy", (obj @ Ti[:3, :3].T + Ti[:3, 3]).astype("<f4"))
    lines = ["pair_id\tsource\ttarget\tnn_frac"]
    for k, (s, t) in enumerate(pairs):
        lines.append(f"bun_{k:02d}\t{s}\t{t}\t0.5")
        np.savetxt(root / "gt" / f"bun_{k:02d}.txt", np.linalg.inv(T_by_scan[t]) @ T_by_scan[s])
    (root / "pairs.tsv").write_text("\n".join(lines) + "\n")


def _T(yaw: float, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("y", yaw, degrees=True).as_matrix()
    T[:3, 3] = t
    return T


def test_bunny_sequence_chains_pairwise_ground_truth(tmp_path):
    scans = {"bun000": _T(0), "bun045": _T(45, (0.01, 0, 0)), "bun090": _T(90, (0, 0.02, 0)),
             "bun180": _T(180, (0, 0, 0.01))}
    # bun180 is only linked through bun090, and one pair is stored the other way round.
    _fake_bunny(tmp_path, scans, [("bun045", "bun000"), ("bun000", "bun090"),
                                  ("bun180", "bun090")])
    seq = Q.load_bunny_sequence(tmp_path, order=("bun000", "bun045", "bun090", "bun180"))
    rel = seq.relative_poses()
    for k, name in enumerate(("bun000", "bun045", "bun090", "bun180")):
        np.testing.assert_allclose(rel[k], scans[name], atol=1e-9)
        # Every scan lands on the first one under its pose.
        assert _near_fraction(seq.clouds[0], seq.clouds[k], rel[k], 1e-5) == 1.0
    assert np.all(np.diff(seq.stamps_ns) == 10**9) and seq.info["source"] == "bunny"


def test_bunny_sequence_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="pairs.tsv"):
        Q.load_bunny_sequence(tmp_path / "nowhere")
    _fake_bunny(tmp_path, {"a": _T(0), "b": _T(30), "c": _T(60)}, [("b", "a")])
    with pytest.raises(ValueError, match=r"\['c'\]"):
        Q.load_bunny_sequence(tmp_path, order=("a", "b", "c"))
    with pytest.raises(FileNotFoundError, match="zz.npy"):
        _fake_bunny(tmp_path / "x", {"a": _T(0), "zz": _T(9)}, [("zz", "a")])
        (tmp_path / "x" / "scans" / "zz.npy").unlink()
        Q.load_bunny_sequence(tmp_path / "x", order=("a", "zz"))


# --------------------------------------------------------------------------------------------
# Sequence bags
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_sequence_bag_round_trip(tmp_path, room_sequence, storage):
    out = tmp_path / "seq"
    assert B.write_sequence(out, room_sequence, storage=storage) == 6
    frames = list(B.read_sequence(out))
    assert [f.stamp_ns for f in frames] == list(room_sequence.stamps_ns)
    for f, cloud, T in zip(frames, room_sequence.clouds, room_sequence.poses):
        np.testing.assert_array_equal(f.cloud, cloud)
        np.testing.assert_allclose(f.T_world_cloud, T, atol=1e-12)
        assert f.frame_id == Q.FRAME_ID
    assert B.read_sequence_info(out) == room_sequence.info


def test_sequence_bag_topics_types_and_frames(tmp_path, room_sequence):
    from rosbags.rosbag2 import Reader

    out = tmp_path / "seq"
    B.write_sequence(out, room_sequence.subset([0, 1]), storage="mcap")
    with Reader(out) as reader:
        assert {c.topic: c.msgtype for c in reader.connections} == {
            "/cegc/cloud": "sensor_msgs/msg/PointCloud2",
            "/cegc/cloud_ground_truth": "geometry_msgs/msg/PoseStamped",
            "/cegc/sequence_info": "std_msgs/msg/String"}
        assert {c.topic: c.msgcount for c in reader.connections} == {
            "/cegc/cloud": 2, "/cegc/cloud_ground_truth": 2, "/cegc/sequence_info": 1}


def test_sequence_bag_without_ground_truth(tmp_path, room_sequence):
    bare = Q.Sequence(room_sequence.clouds[:3], None, room_sequence.stamps_ns[:3], "lidar", {})
    out = tmp_path / "seq"
    B.write_sequence(out, bare)
    frames = list(B.read_sequence(out))
    assert len(frames) == 3 and all(f.T_world_cloud is None for f in frames)
    assert frames[0].frame_id == "lidar" and B.read_sequence_info(out) == {}


@pytest.mark.parametrize("storage,ext", [("sqlite3", "db3"), ("mcap", "mcap")])
def test_truncated_sequence_bag_raises_bag_error(tmp_path, room_sequence, storage, ext):
    out = tmp_path / "seq"
    B.write_sequence(out, room_sequence, storage=storage)
    data = (out / f"seq.{ext}").read_bytes()
    (out / f"seq.{ext}").write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises(B.BagError, match="seq"):
        list(B.read_sequence(out))


def test_sequence_bag_errors(tmp_path, room_sequence):
    with pytest.raises(B.BagError, match="does not exist"):
        list(B.read_sequence(tmp_path / "none"))
    pair_bag = tmp_path / "pairs"
    B.write_pairs(pair_bag, [B.BagPair(np.zeros((3, 3)), np.ones((3, 3)), None, 0)])
    with pytest.raises(B.BagError, match="not a sequence bag"):
        list(B.read_sequence(pair_bag))
    out = tmp_path / "seq"
    B.write_sequence(out, room_sequence.subset([0]))
    with pytest.raises(B.BagError, match="exists already"):
        B.write_sequence(out, room_sequence)
    backwards = Q.Sequence(room_sequence.clouds[:2], None, room_sequence.stamps_ns[1::-1])
    with pytest.raises(B.BagError, match="increase"):
        B.write_sequence(tmp_path / "back", backwards)


def test_lidar_sequence_is_level_sweeps_and_scale_grows_every_length():
    from cegc_ros.data.sequences import make_lidar_sequence

    small = make_lidar_sequence(0, 3)
    big = make_lidar_sequence(0, 3, scale=10.0)
    assert np.diff(small.stamps_ns).tolist() == [10**8, 10**8]           # 10 Hz
    for T in small.poses:                                                  # z up, level
        np.testing.assert_allclose(T[:3, 2], [0.0, 0.0, 1.0], atol=1e-12)
        assert T[2, 3] == pytest.approx(1.2)
    step = np.linalg.norm(small.poses[1][:3, 3] - small.poses[0][:3, 3])
    assert step == pytest.approx(0.04, rel=0.05)                           # 0.4 m/s
    np.testing.assert_allclose(big.poses[:, :3, 3], 10.0 * small.poses[:, :3, 3])
    np.testing.assert_allclose(big.clouds[0], 10.0 * small.clouds[0], rtol=1e-6)
    r = np.linalg.norm(small.clouds[0], axis=1)
    assert len(small.clouds[0]) > 10_000 and r.min() >= 0.5                 # the sensor's min range
    assert big.info["room_size"] == pytest.approx([10 * x for x in small.info["room_size"]])
