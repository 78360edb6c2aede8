"""The gscan_ros nodes in one process, spun by one SingleThreadedExecutor.

One thread runs every callback to its end (the lock-step stack is sequential anyway, and
Python callbacks share the GIL), so when the spinning stops no callback is left running
while the nodes are destroyed: a recorder's bag is never closed under a write.

The same node classes and parameters as `launch/gscan.launch.py`, for machines without
`ros2 launch` (`gscan-ros bringup`) and for the demo, which drives the stack with a
GscanCommander in the same process.
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from pathlib import Path

from gscan_ros.errors import GscanError
from gscan_ros.world.types import GRID_SIZE


@dataclass(frozen=True)
class StackOptions:
    """What `gscan-ros bringup` / `demo` set; each field becomes a node parameter.

    `max_steps` None keeps policy_node's default (`gscan_ros.model.policy.MAX_STEPS`), named
    there only: importing it here would load torch into every `gscan-ros` command line.
    """

    checkpoint: Path | None = None
    parser: str = ""
    dataset: Path | None = None
    split: str = "test"
    index: int = 0
    seed: int = 0
    grid_size: int = GRID_SIZE
    max_steps: int | None = None
    record: Path | None = None
    record_images: bool = False
    overwrite: bool = False


class Stack:
    """The nodes of one stack in rclpy's default context, spun by a SingleThreadedExecutor.

    Use as a context manager; `spin()` blocks until SIGINT/SIGTERM, `start()` spins in a
    background thread (the demo). Leaving the context destroys the nodes, which closes
    the recorder's bag. Signals never interrupt a callback (`common.stop_requests`).
    """

    def __init__(self, options: StackOptions):
        self.options = options
        self.nodes = []
        self._thread: threading.Thread | None = None

    def __enter__(self) -> "Stack":
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions

        rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
        try:
            self.nodes = self._build()
        except BaseException:
            self._destroy()
            rclpy.try_shutdown()
            raise
        self.executor = SingleThreadedExecutor()
        for node in self.nodes:
            self.executor.add_node(node)
        return self

    def _build(self) -> list:
        from gscan_ros.nodes.parser_node import ParserNode
        from gscan_ros.nodes.policy_node import PolicyNode
        from gscan_ros.nodes.world_simulator_node import WorldSimulatorNode

        o = self.options
        checkpoint = str(o.checkpoint) if o.checkpoint else ""
        self.nodes = []  # filled as built, so a failure destroys what exists
        self.nodes.append(WorldSimulatorNode(parameter_overrides=_params(
            dataset=str(o.dataset) if o.dataset else "", split=o.split, index=o.index, seed=o.seed,
            grid_size=o.grid_size,
        )))
        self.nodes.append(ParserNode(parameter_overrides=_params(checkpoint=checkpoint, parser=o.parser)))
        cap = {} if o.max_steps is None else {"max_steps": o.max_steps}
        self.nodes.append(PolicyNode(parameter_overrides=_params(checkpoint=checkpoint, **cap)))
        if o.record is not None:
            from gscan_ros.nodes.episode_recorder_node import EpisodeRecorderNode

            self.nodes.append(EpisodeRecorderNode(parameter_overrides=_params(
                bag_dir=str(o.record), include_images=o.record_images, overwrite=o.overwrite,
            )))
        return self.nodes

    def node(self, cls):
        """The stack's node of class `cls`."""
        return next(n for n in self.nodes if isinstance(n, cls))

    def spin(self) -> None:
        """Spin until SIGINT or SIGTERM (from the main thread); a second signal raises KeyboardInterrupt."""
        from gscan_ros.nodes.common import spin_until, stop_requests

        with stop_requests() as stop:
            spin_until(self.executor, stop)

    def start(self) -> None:
        """Spin in a background thread (the caller drives the stack, e.g. with a GscanCommander)
        until the stack is left; Ctrl-C reaches the caller's thread as KeyboardInterrupt."""
        self._thread = threading.Thread(target=self._spin_in_background, name="gscan-stack", daemon=True)
        self._thread.start()

    def _spin_in_background(self) -> None:
        from rclpy.executors import ExternalShutdownException

        try:
            self.executor.spin()
        except ExternalShutdownException:
            pass

    def wait_until_recording(self, timeout: float = 30.0) -> None:
        """With a recorder: wait until it has the world state, so the next episode is recorded."""
        from gscan_ros.nodes.episode_recorder_node import EpisodeRecorderNode

        recorders = [n for n in self.nodes if isinstance(n, EpisodeRecorderNode)]
        deadline = time.monotonic() + timeout
        while not all(r.ready for r in recorders):
            if time.monotonic() > deadline:
                raise GscanError(f"timed out after {timeout:.0f} s waiting for episode_recorder_node "
                                 "to receive the world state")
            time.sleep(0.005)

    def __exit__(self, *exc_info) -> None:
        import rclpy

        if hasattr(self, "executor"):
            self.executor.shutdown()
        if self._thread is not None:
            self._thread.join(timeout=10)
        self._destroy()
        rclpy.try_shutdown()

    def _destroy(self) -> None:
        for node in reversed(self.nodes):
            node.destroy_node()
        self.nodes = []


def _params(**values):
    from rclpy.parameter import Parameter

    return [Parameter(name, value=value) for name, value in values.items()]
