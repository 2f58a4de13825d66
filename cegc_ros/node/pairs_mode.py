"""Pairs mode: source_cloud and target_cloud paired by stamp, one registration per pair.

A *mode* is the small object the node holds to turn incoming clouds into registration jobs:
it names the topics it reads (``inputs``: side -> relative topic), takes each message
(:meth:`offer`), says what it produced (an :class:`Offer`: a job and/or clouds it gave up
on) and hears about each result (:meth:`on_result`); it adds its own outputs
(:meth:`create_outputs`), builds the worker that runs its jobs (:meth:`make_worker`) and its
/diagnostics key-values (:meth:`diagnostics`). cegc_ros/node/sequential_mode.py is the
other. The node does the rest (counting, the mailbox, the engine, publishing), so another
mode sits beside this one without a branch through the node.
"""

from __future__ import annotations

from typing import Any

from cegc_ros.config import SyncConfig
from cegc_ros.node.support import Job, Offer
from cegc_ros.node.worker import RegistrationWorker
from cegc_ros.pairing import ApproximatePairer


class PairsMode:
    """Pairs the two inputs by header stamp within ``sync.slop`` (cegc_ros/pairing.py)."""

    name = "pairs"
    inputs = {"source": "source_cloud", "target": "target_cloud"}

    def __init__(self, sync: SyncConfig) -> None:
        self.pairer: ApproximatePairer[Any] = ApproximatePairer(sync.slop, sync.buffer_size)

    def configure(self, sync: SyncConfig) -> None:
        """Apply changed ``sync.*`` settings (from the next message on)."""
        self.pairer.slop_s = sync.slop
        self.pairer.buffer_size = sync.buffer_size

    def offer(self, side: str, stamp_ns: int, msg: Any, now: float) -> Offer:
        """Take one message of ``side``; a job when it completes a pair."""
        result = self.pairer.add(side, stamp_ns, msg)  # type: ignore[arg-type]
        offer = Offer()
        for u in result.unpaired:
            other = "target" if u.side == "source" else "source"
            offer.unpaired_sides.append(u.side)
            offer.unpaired.append(f"{u.side} cloud at stamp {u.stamp_ns / 1e9:.3f} s found no "
                                  f"{other} cloud within sync.slop = {self.pairer.slop_s} s; "
                                  "dropped")
        if result.pair is not None:
            offer.job = Job(result.pair.source.msg, result.pair.target.msg, now)
        return offer

    def on_result(self, job: Job, result: Any) -> None:
        """Pairs are independent: nothing to remember."""

    def reset(self) -> None:
        """Forget the clouds still waiting for a partner."""
        self.pairer.flush()

    def create_outputs(self, node: Any) -> None:
        """No outputs beyond the node's common ones."""

    def make_worker(self, node: Any) -> Any:
        """The worker that registers each pair with the node's engine and publishes it."""
        return RegistrationWorker(node.engine, node.stats, node._log, settings=lambda: node.cfg,
                                  publish=node.publish_result, on_result=self.on_result,
                                  info=node.get_logger().info, report=node.report_pair)

    def diagnostics(self, stats: Any) -> dict[str, str]:
        """No /diagnostics key-values of its own."""
        return {}
