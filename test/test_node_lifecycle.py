"""register_lifecycle_node over real DDS: every transition through the lifecycle services.

Subprocess nodes (real engine, small config), driven by lifecycle_msgs ChangeState / GetState:
sequential mode through configure -> activate -> deactivate -> activate -> deactivate ->
cleanup -> configure -> shutdown, checking what the node does in each state (no input and no
output while inactive, odometry that continues after a reactivation, the engine process gone
after cleanup, a clean exit after shutdown); pairs mode (a pose while active, shutdown from
active); a broken checkpoint that fails configure with the reason.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import ros_helpers as rh

rclpy = pytest.importorskip("rclpy")

from cegc_ros.data.sequences import make_room_sequence
from cegc_ros.engine import default_weights
from cegc_ros.spinning import Spinner

CHECKPOINT = Path(os.environ.get("CEGC_TEST_CHECKPOINT", default_weights()))
BASE_ARGS = ["--ros-args", "--params-file", f"{rh.REPO}/params/register_node.yaml",
             "-p", "input.reliable:=true", "-p", "preprocess.num_points:=256",
             "-p", "diagnostics.period:=0.5", "-p", "engine.device:=cpu"]
TIMEOUT = 120.0          # a transition that starts the engine on a busy 2-core machine

pytestmark = pytest.mark.skipif(not CHECKPOINT.is_file(), reason=f"no checkpoint {CHECKPOINT}")


def start(name: str, *extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "cegc_ros.node.lifecycle_main", *BASE_ARGS,
                             "-r", f"__node:={name}", *extra], env=rh.ros_env(), cwd=rh.REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def finish(proc: subprocess.Popen, timeout: float = 30.0) -> tuple[int, str]:
    """(exit code, output) of a node process that should be exiting; killed if it does not."""
    try:
        out = proc.communicate(timeout=timeout)[0]
    except subprocess.TimeoutExpired:
        proc.kill()
        out = proc.communicate()[0]
        return -9, out
    return proc.returncode, out


class Manager:
    """A lifecycle client of one node plus a recorder of its outputs (in its own context)."""

    def __init__(self, name: str) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped
        from lifecycle_msgs.srv import ChangeState, GetState
        from nav_msgs.msg import Odometry
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2

        self.name = name
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(f"lifecycle_manager_{name}", context=self.context)
        qos = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
        self.pub = {t: self.node.create_publisher(PointCloud2, f"/{t}", qos)
                    for t in ("cloud", "source_cloud", "target_cloud")}
        self.change = self.node.create_client(ChangeState, f"/{name}/change_state")
        self.get = self.node.create_client(GetState, f"/{name}/get_state")
        self.recorder = rh.OutputRecorder(f"/{name}: registration")
        for key, kind, topic in (("odometry", Odometry, f"/{name}/odometry"),
                                 ("pose", PoseStamped, f"/{name}/pose"),
                                 ("diagnostics", DiagnosticArray, "/diagnostics")):
            self.node.create_subscription(kind, topic, self.recorder.keeper(key), 50)
        self.outputs = self.recorder.outputs
        self.diagnostics = self.recorder.diagnostics
        self.ex = SingleThreadedExecutor(context=self.context)
        self.ex.add_node(self.node)
        self.spinner = Spinner(self.ex)

    def _call(self, client, request, repeat: bool = False):
        """The answer to ``request``; ``repeat`` (queries only) sends it again while unanswered
        (rh.call_idempotent), a transition is sent once."""
        assert client.wait_for_service(timeout_sec=TIMEOUT), f"no service {client.srv_name}"
        if repeat:
            answer = rh.call_idempotent(client, request, TIMEOUT)
        else:
            future = client.call_async(request)
            answer = future.result() if rh.wait_for(future.done, TIMEOUT) else None
        assert answer is not None, f"{client.srv_name}: no answer"
        return answer

    def state(self) -> str:
        from lifecycle_msgs.srv import GetState

        return self._call(self.get, GetState.Request(), repeat=True).current_state.label

    def transition(self, transition_id: int) -> bool:
        from lifecycle_msgs.srv import ChangeState

        req = ChangeState.Request()
        req.transition.id = transition_id
        return bool(self._call(self.change, req).success)

    def close(self) -> None:
        self.spinner.stop()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


@pytest.fixture(scope="module")
def sequence():
    return make_room_sequence(3, 12, frame_step=3, pixel_stride=8)


def _send_and_wait(mgr: Manager, seq, k: int) -> None:
    stamp = int(seq.stamps_ns[k])
    mgr.pub["cloud"].publish(rh.cloud(seq.clouds[k], seq.frame_id, stamp))
    assert rh.wait_for(lambda: stamp in {rh.stamp_of(m) for m in mgr.outputs("odometry")},
                       TIMEOUT), (k, mgr.diagnostics())


def _odometry(mgr: Manager, seq, k: int) -> np.ndarray:
    from msg_adapters.nav import odometry_to_matrix

    stamp = int(seq.stamps_ns[k])
    return next(odometry_to_matrix(m)[0] for m in mgr.outputs("odometry")
                if rh.stamp_of(m) == stamp)


def _pid_gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    # A zombie until its parent (the node) reaps it: read its state.
    try:
        return Path(f"/proc/{pid}/stat").read_text().split()[2] == "Z"
    except OSError:
        return True


def test_every_transition_in_sequential_mode(sequence):
    from lifecycle_msgs.msg import Transition

    seq = sequence
    gt = seq.relative_poses()
    proc = start("lc_seq", "-p", f"engine.checkpoint:={CHECKPOINT}",
                 "-p", "input.mode:=sequential")
    mgr = Manager("lc_seq")
    try:
        assert mgr.state() == "unconfigured"
        assert mgr.node.count_publishers("/lc_seq/odometry") == 0

        # configure: parameters and engine; still no topics (they come with activate).
        assert mgr.transition(Transition.TRANSITION_CONFIGURE)
        assert mgr.state() == "inactive"
        assert mgr.pub["cloud"].get_subscription_count() == 0
        assert mgr.node.count_publishers("/lc_seq/odometry") == 0

        # activate: clouds in, odometry out.
        assert mgr.transition(Transition.TRANSITION_ACTIVATE)
        assert mgr.state() == "active"
        assert rh.wait_for(lambda: mgr.pub["cloud"].get_subscription_count() > 0, TIMEOUT)
        for k in range(5):
            _send_and_wait(mgr, seq, k)
        assert rh.wait_for(lambda: mgr.diagnostics().get("mode") == "sequential", TIMEOUT)
        engine_pid = int(mgr.diagnostics()["engine_pid"])

        # deactivate: the node stops reading and publishing.
        assert mgr.transition(Transition.TRANSITION_DEACTIVATE)
        assert mgr.state() == "inactive"
        assert rh.wait_for(lambda: mgr.pub["cloud"].get_subscription_count() == 0, TIMEOUT)
        n_out, n_diag = len(mgr.outputs("odometry")), len(mgr.outputs("diagnostics"))
        mgr.pub["cloud"].publish(rh.cloud(seq.clouds[5], seq.frame_id, int(seq.stamps_ns[5])))
        time.sleep(2.0)                 # four diagnostics periods: nothing may come
        assert len(mgr.outputs("odometry")) == n_out
        assert all(st.name != "/lc_seq: registration"
                   for arr in mgr.outputs("diagnostics")[n_diag:] for st in arr.status)

        # activate again: the odometry continues from its state (not a new odometry frame).
        assert mgr.transition(Transition.TRANSITION_ACTIVATE)
        assert mgr.state() == "active"
        assert rh.wait_for(lambda: mgr.pub["cloud"].get_subscription_count() > 0, TIMEOUT)
        for k in range(6, 9):
            _send_and_wait(mgr, seq, k)
        T, G = _odometry(mgr, seq, 8), gt[8]
        assert np.linalg.norm(G[:3, 3]) > 0.2                    # far from a restart at 0
        assert np.linalg.norm(T[:3, 3] - G[:3, 3]) < 0.05
        assert int(mgr.diagnostics().get("engine_pid", -1)) == engine_pid

        # deactivate + cleanup: the engine process ends (the model is released).
        assert mgr.transition(Transition.TRANSITION_DEACTIVATE)
        assert mgr.transition(Transition.TRANSITION_CLEANUP)
        assert mgr.state() == "unconfigured"
        assert rh.wait_for(lambda: _pid_gone(engine_pid), 30.0)

        # configure again (a new engine), then shut down from inactive: the process exits 0.
        assert mgr.transition(Transition.TRANSITION_CONFIGURE)
        assert mgr.state() == "inactive"
        assert mgr.transition(Transition.TRANSITION_INACTIVE_SHUTDOWN)
        code, out = finish(proc)
        assert code == 0, out
        assert "shut down" in out
        assert "unconfigured: waiting for the configure transition" in out, out
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        mgr.close()


def test_pairs_mode_poses_while_active_and_shutdown_from_active():
    from lifecycle_msgs.msg import Transition

    from cegc_ros.data.protocols import make_pairs

    pair = make_pairs("7scenes", "test", 1)[0]
    proc = start("lc_pairs", "-p", f"engine.checkpoint:={CHECKPOINT}")
    mgr = Manager("lc_pairs")
    try:
        assert mgr.transition(Transition.TRANSITION_CONFIGURE)
        assert mgr.transition(Transition.TRANSITION_ACTIVATE)
        assert mgr.state() == "active"
        assert rh.wait_for(lambda: all(mgr.pub[t].get_subscription_count() > 0
                                       for t in ("source_cloud", "target_cloud")), TIMEOUT)
        stamp = 5 * 10**9
        mgr.pub["source_cloud"].publish(rh.cloud(pair.source, "src", stamp))
        mgr.pub["target_cloud"].publish(rh.cloud(pair.target, "tgt", stamp))
        assert rh.wait_for(lambda: len(mgr.outputs("pose")) == 1, TIMEOUT), mgr.diagnostics()
        pose = mgr.outputs("pose")[0]
        assert rh.stamp_of(pose) == stamp and pose.header.frame_id == "tgt"
        assert rh.wait_for(lambda: mgr.diagnostics().get("mode") == "pairs", TIMEOUT), mgr.diagnostics()
        assert mgr.transition(Transition.TRANSITION_ACTIVE_SHUTDOWN)
        code, out = finish(proc)
        assert code == 0, out
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        mgr.close()


def test_broken_checkpoint_fails_configure_with_the_reason(tmp_path):
    from lifecycle_msgs.msg import Transition

    broken = tmp_path / "broken.pt"
    broken.write_bytes(b"not a checkpoint" * 10)
    proc = start("lc_broken", "-p", f"engine.checkpoint:={broken}")
    mgr = Manager("lc_broken")
    try:
        assert mgr.state() == "unconfigured"
        assert not mgr.transition(Transition.TRANSITION_CONFIGURE)
        assert mgr.state() == "unconfigured"
        assert proc.poll() is None                          # the node lives on
        assert mgr.transition(Transition.TRANSITION_UNCONFIGURED_SHUTDOWN)
        code, out = finish(proc)
        assert code == 0, out
        failed = [ln for ln in out.splitlines() if "configure failed" in ln]
        assert len(failed) == 1, out
        assert "CheckpointError" in failed[0] and str(broken) in failed[0]
        assert "Traceback" not in out
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        mgr.close()
