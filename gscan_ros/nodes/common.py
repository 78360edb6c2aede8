"""What the gscan_ros nodes share: topic names, QoS profiles, the status channel, `run()`.

Topic names are relative (DESIGN.md "ROS interface"), so a whole stack can be pushed
into a namespace with `--ros-args -r __ns:=/robot1`.
"""
from __future__ import annotations

import functools
import re
import sys
import time
import traceback
from collections.abc import Callable
from typing import TypeVar

import rclpy
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from gscan_ros.errors import GscanError

COMMAND = "command"
COMMAND_GRAPH = "command_graph"
STATUS = "status"
OBSERVATION = "observation"
SITUATION = "situation"  # gSCAN situation JSON of the current world state (for recorders)
WORLD_RESET = "world_reset"  # std_msgs/Header stamped with the time the world was (re)loaded
WORLD_IMAGE = "world_image"
ACTION = "action"
ATTENTION_PREFIX = "attention"
SIZE_ORDERING = f"{ATTENTION_PREFIX}/size_ordering"  # (-att_small + att_big) / 2, commands with a size word
RESET_WORLD = "reset_world"

# World-state-like topics: a late subscriber still gets the current state (DESIGN.md).
LATCHED_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
# The world simulator's state streams (observation, situation, world_image): latched for
# late joiners like LATCHED_QOS, but the writer keeps the last 64 states, because a
# reliable writer that keeps only the newest drops a state a busy recorder has not yet
# acknowledged when the policy steps fast (~5 ms a step), and the recorder then cannot
# pair the episode's actions. A depth-1 reader (the policy) still sees only the newest.
LATCHED_STATE_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=64,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
# A reader of latched topics that must see every state, not just the newest (recorders,
# test probes): it gets the stored sample on joining and queues later ones while busy.
LATCHED_LOG_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1000,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
# Event streams (command, action, status). The queue is deep enough that a burst of
# 1000 rejected commands is reported in full, and bounded so a flood cannot grow memory.
EVENT_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1000,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
# Viewer-only streams (attention maps): losing one frame is harmless.
VIEWER_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=5,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)

ECHO_CHARS = 60  # how much of a rejected input a status line quotes
STATUS_CHARS = 300  # longest status line
WARNING_INTERVAL_S = 1.0  # at most one rejection warning per interval in the log


def describe(text: str, *, read_only: bool = True) -> ParameterDescriptor:
    """Parameter descriptor with a description (shown by `ros2 param describe`)."""
    return ParameterDescriptor(description=text, read_only=read_only)


def quote(value: object) -> str:
    """repr() of a rejected input, shortened so a 10 kB command gives a one-line status."""
    text = repr(value)
    return text if len(text) <= ECHO_CHARS else f"{text[:ECHO_CHARS]}... ({len(str(value))} chars)"


def topic_token(word: str) -> str:
    """A valid ROS name token for a graph word: "while spinning" -> "while_spinning", "<root>" -> "root"."""
    token = re.sub(r"[^0-9A-Za-z]+", "_", word).strip("_")
    return token if token and not token[0].isdigit() else f"w_{token}"


class StatusReporter:
    """Publishes one human-readable line per event or rejected input on `status`, and logs it.

    Lines are prefixed with the node name and capped at STATUS_CHARS, so an error that
    quotes a 10 kB input still yields one short line. Every rejection is published, but
    at most one per WARNING_INTERVAL_S is logged as a warning (the others at debug
    level, counted in the next warning): rclpy's logger costs ~0.5 ms a call, which a
    flood of bad input must not multiply.
    """

    def __init__(self, node: Node) -> None:
        self._node = node
        self._pub = node.create_publisher(String, STATUS, EVENT_QOS)
        self._next_warning = 0.0
        self._unlogged = 0

    def info(self, text: str) -> None:
        line = self._line(text)
        self._pub.publish(String(data=f"{self._node.get_name()}: {line}"))
        self._node.get_logger().info(line)

    def reject(self, text: str) -> None:
        line = self._line(text)
        self._pub.publish(String(data=f"{self._node.get_name()}: {line}"))
        now = time.monotonic()
        if now < self._next_warning:
            self._unlogged += 1
            self._node.get_logger().debug(line)
            return
        more = f" (and {self._unlogged} more rejections, see the status topic)" if self._unlogged else ""
        self._node.get_logger().warning(line + more)
        self._next_warning, self._unlogged = now + WARNING_INTERVAL_S, 0

    @staticmethod
    def _line(text: str) -> str:
        line = " ".join(text.split())
        return line if len(line) <= STATUS_CHARS else line[: STATUS_CHARS - 3] + "..."


CallbackT = TypeVar("CallbackT", bound=Callable[..., None])


def guarded(callback: CallbackT) -> CallbackT:
    """Decorate a node callback so no input can kill the node (the node has `self.status`).

    A `GscanError` is a rejected input: its message goes to `status`. Anything else is a
    bug in gscan_ros: the traceback goes to the log and a short line to `status`, and the
    node keeps serving the next message.
    """

    @functools.wraps(callback)
    def guarded_callback(self, *args, **kwargs):
        try:
            return callback(self, *args, **kwargs)
        except GscanError as exc:
            self.status.reject(str(exc))
        except Exception as exc:  # noqa: BLE001 - a node must survive its own bugs
            self.get_logger().error(traceback.format_exc())
            self.status.reject(f"internal error in {callback.__name__}: {type(exc).__name__}: {exc}")
        return None

    return guarded_callback  # type: ignore[return-value]


def guarded_trigger(failure: str) -> Callable[[CallbackT], CallbackT]:
    """`guarded` for a std_srvs/Trigger service: any exception becomes `success=False`.

    The response message is `<failure>: <reason>`, `status` gets the same line, and the
    node keeps serving (an exception escaping a service callback ends the node).
    """

    def decorate(callback: CallbackT) -> CallbackT:
        @functools.wraps(callback)
        def guarded_callback(self, request, response):
            try:
                return callback(self, request, response)
            except GscanError as exc:
                reason = str(exc)
            except Exception as exc:  # noqa: BLE001 - a node must survive its own bugs
                self.get_logger().error(traceback.format_exc())
                reason = f"internal error in {callback.__name__}: {type(exc).__name__}: {exc}"
            response.success, response.message = False, f"{failure}: {reason}"
            self.status.reject(response.message)
            return response

        return guarded_callback  # type: ignore[return-value]

    return decorate


NodeT = TypeVar("NodeT", bound=Node)


def run(node_factory: Callable[[], NodeT], args: list[str] | None = None) -> int:
    """`main()` of a node executable: init, spin until SIGINT/SIGTERM, clean up.

    A configuration error (bad parameter, missing checkpoint) is one line on stderr and
    exit status 1, like the `gscan-ros` CLI.
    """
    rclpy.init(args=args)
    node = None
    try:
        node = node_factory()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except GscanError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
