"""The shipped Fast DDS profile for publishers of huge clouds (params/fastdds_large_clouds.xml).

What it sets, where an installed package finds it, how ``paths.fastdds_profile`` puts it in
the environment (never over the user's own setting), and that Fast DDS in this venv reads it
in a publishing process: a process that names a broken copy gets Fast DDS's XML errors, one
that names the shipped file gets none and delivers a multi-fragment cloud. No timing: what the
0.1 s heartbeat buys is measured by ``bench_node`` (docs/node.md).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
import ros_helpers as rh

from cegc_ros import paths

REPO = Path(__file__).resolve().parents[1]
PROFILE = REPO / "params" / paths.FASTDDS_PROFILE
NS = "{http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles}"
ENV = paths.FASTDDS_PROFILE_ENV


def _leaves(elem: ET.Element, prefix: str = "") -> dict[str, str]:
    out = {}
    for child in elem:
        name = f"{prefix}/{child.tag.removeprefix(NS)}"
        if len(child):
            out.update(_leaves(child, name))
        else:
            out[name] = (child.text or "").strip()
    return out


def test_the_profile_sets_only_the_writers_heartbeat_period_to_100_ms():
    root = ET.parse(PROFILE).getroot()
    assert root.tag == f"{NS}profiles"
    profiles = list(root)
    assert [p.tag for p in profiles] == [f"{NS}data_writer"]
    assert profiles[0].get("is_default_profile") == "true"   # every writer of the process
    leaves = _leaves(profiles[0])
    assert leaves == {"/times/heartbeatPeriod/sec": "0",
                      "/times/heartbeatPeriod/nanosec": "100000000"}
    period = (int(leaves["/times/heartbeatPeriod/sec"])
              + int(leaves["/times/heartbeatPeriod/nanosec"]) * 1e-9)
    assert period == pytest.approx(0.1)


def test_a_checkout_finds_its_own_profile():
    assert paths.shipped_fastdds_profile() == PROFILE


def test_an_installed_package_finds_the_profile_through_the_ament_index(tmp_path):
    site = tmp_path / "site-packages" / "cegc_ros"
    site.mkdir(parents=True)
    (site / "__init__.py").write_text("")
    shutil.copy(REPO / "cegc_ros" / "paths.py", site / "paths.py")
    prefix = tmp_path / "prefix"
    (prefix / "share/ament_index/resource_index/packages").mkdir(parents=True)
    (prefix / "share/ament_index/resource_index/packages/cegc_ros").write_text("")
    (prefix / "share/cegc_ros/params").mkdir(parents=True)
    shutil.copy(PROFILE, prefix / "share/cegc_ros/params" / paths.FASTDDS_PROFILE)
    env = dict(os.environ, PYTHONPATH=str(site.parent), AMENT_PREFIX_PATH=str(prefix))
    env.pop(ENV, None)
    code = ("import os; from cegc_ros import paths\n"
            "with paths.fastdds_profile() as p: print(p, os.environ[paths.FASTDDS_PROFILE_ENV])")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env=env, cwd=tmp_path, timeout=60)
    assert proc.returncode == 0, proc.stderr
    installed = str(prefix / "share/cegc_ros/params" / paths.FASTDDS_PROFILE)
    assert proc.stdout.split() == [installed, installed]


@pytest.mark.skipif(not os.environ.get("CEGC_ROS_BOOTSTRAP"),
                    reason="checks the bootstrap's install; run via "
                           "`python3 -m cegc_ros.bootstrap test`")
def test_the_bootstrap_install_ships_the_profile():
    share = paths.share_dir()
    assert share == Path(sys.prefix) / "share" / "cegc_ros"
    assert (share / "params" / paths.FASTDDS_PROFILE).read_bytes() == PROFILE.read_bytes()


# --- the environment --------------------------------------------------------------------


def test_default_names_the_shipped_profile_for_the_block_only(monkeypatch, tmp_path):
    monkeypatch.delenv(ENV, raising=False)
    monkeypatch.chdir(tmp_path)
    with paths.fastdds_profile() as chosen:
        assert chosen == str(PROFILE) == os.environ[ENV]
    assert ENV not in os.environ


@pytest.mark.parametrize("choice", ["default", "none"])
def test_a_users_setting_is_kept_by_default_and_restored_after_none(monkeypatch, tmp_path,
                                                                   choice):
    monkeypatch.setenv(ENV, "/opt/robot/my_profiles.xml")
    monkeypatch.chdir(tmp_path)
    with paths.fastdds_profile(choice) as chosen:
        if choice == "default":
            assert chosen == os.environ[ENV] == "/opt/robot/my_profiles.xml"
        else:
            assert chosen is None and ENV not in os.environ
    assert os.environ[ENV] == "/opt/robot/my_profiles.xml"


def test_an_empty_setting_counts_as_unset(monkeypatch, tmp_path):
    # Fast DDS itself fails on an empty name ("realpath failed"): it configures nothing.
    monkeypatch.setenv(ENV, "")
    monkeypatch.chdir(tmp_path)
    with paths.fastdds_profile() as chosen:
        assert chosen == str(PROFILE) == os.environ[ENV]
    assert os.environ[ENV] == ""


def test_a_profiles_file_in_the_working_directory_is_left_to_fast_dds(monkeypatch, tmp_path):
    monkeypatch.delenv(ENV, raising=False)
    monkeypatch.chdir(tmp_path)
    (tmp_path / "DEFAULT_FASTRTPS_PROFILES.xml").write_text("<profiles/>")
    with paths.fastdds_profile() as chosen:
        assert chosen == str(tmp_path / "DEFAULT_FASTRTPS_PROFILES.xml")
        assert ENV not in os.environ        # Fast DDS loads that file by itself


def test_an_explicit_path_is_used_and_must_exist(monkeypatch, tmp_path):
    monkeypatch.setenv(ENV, "/opt/robot/my_profiles.xml")
    mine = tmp_path / "mine.xml"
    mine.write_text("<profiles/>")
    with paths.fastdds_profile(str(mine)) as chosen:
        assert chosen == os.environ[ENV] == str(mine)
    with pytest.raises(FileNotFoundError, match="Fast DDS profile /nonexistent.xml is not a"):
        with paths.fastdds_profile("/nonexistent.xml"):
            pass
    assert os.environ[ENV] == "/opt/robot/my_profiles.xml"


# --- Fast DDS reads it ------------------------------------------------------------------

# Publishes a 300k-point PointCloud2 (3.6 MB: many fragments, RELIABLE) from a node created in
# paths.fastdds_profile(argv[1]) every 0.3 s until the file argv[2] exists; prints the profile.
PUBLISHER = r"""
import json, sys, time
from pathlib import Path
import numpy as np
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from cegc_ros import paths
from msg_adapters.point_cloud2 import xyz_to_cloud
rclpy.init()
with paths.fastdds_profile(sys.argv[1]) as chosen:
    node = rclpy.create_node("profile_publisher")
print(json.dumps({"profile": chosen}), flush=True)
pub = node.create_publisher(PointCloud2, "/fastdds_profile_test/cloud",
                            QoSProfile(depth=2, reliability=ReliabilityPolicy.RELIABLE))
msg = xyz_to_cloud(np.random.default_rng(0).normal(size=(300_000, 3)).astype(np.float32),
                   Header(frame_id="f"))
end = time.monotonic() + 120
while time.monotonic() < end and not Path(sys.argv[2]).exists():
    pub.publish(msg)
    time.sleep(0.3)
node.destroy_node()
rclpy.shutdown()
"""

# Receives one cloud with Fast DDS's defaults (no profiles file) and prints its size in bytes.
SUBSCRIBER = r"""
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
rclpy.init()
node = rclpy.create_node("profile_subscriber")
got = []
node.create_subscription(PointCloud2, "/fastdds_profile_test/cloud", got.append,
                         QoSProfile(depth=2, reliability=ReliabilityPolicy.RELIABLE))
while not got:
    rclpy.spin_once(node, timeout_sec=0.2)
print(len(got[0].data), flush=True)
"""


def _publish(choice: str, tmp_path: Path, user_profile: str | None = None
             ) -> tuple[str | None, int, str]:
    """(profile the publisher chose, bytes the subscriber got, the publisher's output)."""
    env = rh.ros_env()
    env.pop(ENV, None)
    sub = subprocess.Popen([sys.executable, "-c", SUBSCRIBER], env=env, cwd=tmp_path,
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    if user_profile is not None:
        env[ENV] = user_profile
    stop = tmp_path / "stop"
    pub = subprocess.Popen([sys.executable, "-c", PUBLISHER, choice, str(stop)], env=env,
                           cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                           text=True)
    try:
        out_sub, _ = sub.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        sub.kill()
        out_sub, _ = sub.communicate()
    finally:
        stop.touch()
        try:
            out_pub, _ = pub.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            pub.kill()
            out_pub, _ = pub.communicate()
    assert pub.returncode == 0, out_pub
    chosen = [json.loads(ln)["profile"] for ln in out_pub.splitlines() if ln.startswith("{")]
    assert len(chosen) == 1, out_pub
    size = out_sub.split()[-1] if out_sub.split() else ""
    return chosen[0], int(size) if size.isdigit() else -1, out_pub


CLOUD_BYTES = 300_000 * 12


def test_a_publisher_with_the_shipped_profile_delivers_a_huge_cloud_without_xml_errors(
        tmp_path):
    chosen, got, out = _publish("default", tmp_path)
    assert chosen == str(paths.shipped_fastdds_profile())
    assert got == CLOUD_BYTES
    assert "XMLPARSER" not in out and "Error" not in out, out


def test_the_users_profile_wins_and_fast_dds_reads_it_in_the_publisher(tmp_path):
    # A copy with a misspelled element: Fast DDS reports it, so the variable the publisher
    # process was given is what Fast DDS read (and the clean run above is not vacuous).
    broken = tmp_path / "broken.xml"
    broken.write_text(PROFILE.read_text().replace("heartbeatPeriod", "heartbeatPeriodX"))
    chosen, got, out = _publish("default", tmp_path, user_profile=str(broken))
    assert chosen == str(broken)
    assert got == CLOUD_BYTES
    assert "XMLPARSER" in out and "heartbeatPeriodX" in out and str(broken) in out, out


def test_cegc_replay_hands_the_shipped_profile_to_fast_dds(tmp_path):
    """replay's default reaches Fast DDS: with shipped_fastdds_profile pointing at a broken
    copy, the replay process reports that copy's XML error; ``none`` reads no file."""
    from cegc_ros.data.bag import write_pairs
    from cegc_ros.data.protocols import make_pairs

    bag = tmp_path / "pairs"
    write_pairs(bag, make_pairs("7scenes", "test", 1))
    broken = tmp_path / "broken.xml"
    broken.write_text(PROFILE.read_text().replace("heartbeatPeriod", "heartbeatPeriodX"))
    code = ("import sys; from pathlib import Path; from cegc_ros import paths\n"
            f"paths.shipped_fastdds_profile = lambda: Path({str(broken)!r})\n"
            "from cegc_ros.tools.replay import main; sys.exit(main(sys.argv[1:]))")
    env = rh.ros_env()
    env.pop(ENV, None)
    outs = {}
    for choice in ("default", "none"):
        proc = subprocess.run([sys.executable, "-c", code, str(bag), "--connect-timeout", "1",
                               "--node-namespace", "/nobody_here", "--fastdds-profile", choice],
                              env=env, cwd=tmp_path, capture_output=True, text=True,
                              timeout=120)
        assert proc.returncode == 1, proc.stderr
        assert proc.stderr.strip().splitlines()[-1].startswith(
            "cegc-replay: no register_node answered within 1.0 s")
        outs[choice] = proc.stdout + proc.stderr
    assert "heartbeatPeriodX" in outs["default"] and str(broken) in outs["default"]
    assert "XMLPARSER" not in outs["none"]


def test_cegc_replay_and_bench_node_name_a_missing_profile_in_one_line(tmp_path):
    from cegc_ros.data.bag import write_pairs
    from cegc_ros.data.protocols import make_pairs

    bag = tmp_path / "pairs"
    write_pairs(bag, make_pairs("7scenes", "test", 1))
    for cmd, prog in ((["-m", "cegc_ros.tools.replay", str(bag)], "cegc-replay"),
                      (["-m", "cegc_ros.tools.bench_node", "--skip", "latency,rate"],
                       "bench_node")):
        proc = subprocess.run([sys.executable, *cmd, "--fastdds-profile", "/nonexistent.xml"],
                              env=rh.ros_env(), cwd=rh.REPO, capture_output=True, text=True,
                              timeout=120)
        assert proc.returncode == 1
        assert (proc.stdout + proc.stderr).strip().splitlines() == [
            f"{prog}: Fast DDS profile /nonexistent.xml is not a file"]
