"""RegisterLifecycleNode: register_node as a managed (lifecycle) node, for lifecycle managers.

The same behaviour as :class:`~cegc_ros.node.ros_node.RegisterNode` (pairs or sequential
mode), with the construction steps of :class:`RegistrationNodeMixin` run from the transitions:

* configure: declare the parameters (first time; later configures re-read their values) and
  start the engine (checkpoint, warm-up). A bad parameter or a broken checkpoint fails the
  transition (back to unconfigured) with the reason logged as an error.
* activate: the mode (kept from an earlier activation), lifecycle publishers, the diagnostics
  timer, the subscriptions and the worker; processing starts.
* deactivate: subscriptions, publishers and timer go, the worker stops (the cloud in progress
  gets 10 s); the engine and the mode's state (the odometry: keyframe, path, velocity) stay,
  so a later activate continues where it stopped.
* cleanup: the engine process stops (the model is released) and the mode is dropped.
* shutdown (from any state): everything is released; ``register_lifecycle_node`` then exits 0.

Started by ``register_lifecycle_node`` (``ros2 run cegc_ros register_lifecycle_node``); the node
is called ``register_node`` like the plain one, with the same parameters and topics.
"""

from __future__ import annotations

from typing import Any

from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn

from cegc_ros.node.engine_process import EngineStartError
from cegc_ros.node.params import NODE_NAME, ParameterError, build_sections, coerce
from cegc_ros.node.ros_node import EngineFactory, RegistrationNodeMixin


class RegisterLifecycleNode(RegistrationNodeMixin, LifecycleNode):
    """register_node, managed. See the module docstring for what each transition does.

    Args:
        engine_factory: as for RegisterNode (tests and benchmarks pass stand-ins).
        node_name: the node's name (``register_node``).
        **node_kwargs: passed to rclpy's LifecycleNode.
    """

    def __init__(self, engine_factory: EngineFactory | None = None,
                 node_name: str = NODE_NAME, **node_kwargs: Any) -> None:
        self._managed_publishers: list[Any] = []
        self._make_lifecycle_publishers = False
        super().__init__(node_name, **node_kwargs)
        self._engine_factory = engine_factory
        self._declared = False
        self.engine: Any = None
        self.mode: Any = None
        self.worker: Any = None
        self.finalized = False
        # Publishers made from here on (by the mixin and the modes) are lifecycle publishers;
        # rclpy's own ones (parameter events, the lifecycle's transition events) were made above.
        self._make_lifecycle_publishers = True
        self.get_logger().info("unconfigured: waiting for the configure transition "
                               f"(lifecycle services on {self.get_fully_qualified_name()}/...)")

    def create_publisher(self, *args: Any, **kwargs: Any) -> Any:
        """A lifecycle publisher (published only while active) for the node's outputs."""
        if not self._make_lifecycle_publishers:
            return super().create_publisher(*args, **kwargs)
        pub = self.create_lifecycle_publisher(*args, **kwargs)
        self._managed_publishers.append(pub)
        return pub

    # -- transitions ----------------------------------------------------------------------
    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            if not self._declared:
                self.setup_parameters()
                self._declared = True
            else:
                self.cfg = build_sections({name: coerce(spec, self.get_parameter(name).value)
                                           for name, spec in self._specs.items()})
            self.start_engine(self._engine_factory)
        except ParameterError as err:
            return self._fail(f"invalid parameter: {err}")
        except EngineStartError as err:
            return self._fail(str(err))
        except Exception as err:  # noqa: BLE001  the transition fails with the reason
            return self._fail(f"{type(err).__name__}: {err}")
        info = self.engine.info
        self.get_logger().info(f"configured: device {info.device}, checkpoint "
                               f"{info.checkpoint}, engine process {info.pid}, mode "
                               f"{self.cfg['input'].mode}")
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        if self.mode is None:
            self.create_mode()
        self.create_outputs()
        self.create_inputs()
        self.start_worker()
        self.worker.engine_settings_changed()   # parameters set while inactive reach the engine
        self.get_logger().info(f"active ({self.mode.name} mode)")
        return super().on_activate(state)        # enables the lifecycle publishers

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._stop_processing(state)
        self.get_logger().info("inactive: processing stopped, state kept")
        return TransitionCallbackReturn.SUCCESS

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release(state)
        self.get_logger().info("cleaned up: engine stopped")
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release(state)
        self.finalized = True
        self.get_logger().info("shut down")
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release(state)
        return TransitionCallbackReturn.SUCCESS

    # -- helpers --------------------------------------------------------------------------
    def _fail(self, reason: str) -> TransitionCallbackReturn:
        self.get_logger().error(f"configure failed: {' '.join(reason.split())}")
        if self.engine is not None:
            self.engine.close()
            self.engine = None
        return TransitionCallbackReturn.FAILURE

    def _stop_processing(self, state: LifecycleState) -> None:
        """Undo activate: inputs, worker, timer, publishers (the mode and engine stay)."""
        for sub in getattr(self, "inputs", []):
            self.destroy_subscription(sub)
        self.inputs = []
        for control in getattr(self, "controls", []):
            if hasattr(control, "srv_type"):
                self.destroy_service(control)
            else:
                self.destroy_subscription(control)
        self.controls = []
        if self.worker is not None and not self.worker.stop(10.0):
            self.get_logger().warning("the registration in progress did not finish in time")
        self.worker = None
        timer = getattr(self, "diag_timer", None)
        if timer is not None:
            self.destroy_timer(timer)
            self.diag_timer = None
        super().on_deactivate(state)              # disables the lifecycle publishers
        for pub in self._managed_publishers:
            self.destroy_lifecycle_publisher(pub)
        self._managed_publishers = []

    def _release(self, state: LifecycleState) -> None:
        """Undo configure (and activate, if active): the engine process stops, the mode goes."""
        self._stop_processing(state)
        if self.engine is not None:
            self.engine.close()
            self.engine = None
        self.mode = None

    def close(self, timeout: float = 10.0) -> bool:
        finished = True
        if self.worker is not None:
            finished = self.worker.stop(timeout)
            self.worker = None
        if self.engine is not None:
            self.engine.close()
            self.engine = None
        return finished
