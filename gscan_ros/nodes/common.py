"""What the gscan_ros nodes share: topic names and QoS from the interface table, status and diagnostics, `run()`.

Topic names are relative (docs/ros.md), so a whole stack can be pushed
into a namespace with `--ros-args -r __ns:=/robot1`. Names, types and offered QoS come
from `gscan_ros.interface` (plain data, shared with the bag code); this module turns
them into rclpy QoSProfiles.
"""
from __future__ import annotations

import contextlib
import functools
import importlib
import logging
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable
from typing import TypeVar

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.exceptions import ParameterException
from rclpy.executors import Executor, ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from std_msgs.msg import Header, String

from gscan_ros import interface
from gscan_ros.errors import GscanError
from gscan_ros.interface import Endpoint, Qos, attention_topic, topic_token  # noqa: F401 - re-exported
from msg_adapters import text_to_cdr
from msg_adapters.header import time_msg

COMMAND = interface.COMMAND.name
COMMAND_GRAPH = interface.COMMAND_GRAPH.name
STATUS = interface.STATUS.name
OBSERVATION = interface.OBSERVATION.name
SITUATION = interface.SITUATION.name  # gSCAN situation JSON of the current world state
WORLD_RESET = interface.WORLD_RESET.name  # std_msgs/Header stamped with the time the world was (re)loaded
WORLD_IMAGE = interface.WORLD_IMAGE.name
ACTION = interface.ACTION.name
EPISODE_STATUS = interface.EPISODE_STATUS.name  # actionlib_msgs/GoalStatus: an episode started / how it ended
ATTENTION_PREFIX = interface.ATTENTION.name
SIZE_ORDERING = interface.SIZE_ORDERING.name  # (-att_small + att_big) / 2, commands with a size word
RESET_WORLD = interface.RESET_WORLD.name
DIAGNOSTICS = interface.DIAGNOSTICS.name  # absolute: every node's DiagnosticStatus

_RELIABILITY = {interface.RELIABLE: ReliabilityPolicy.RELIABLE, interface.BEST_EFFORT: ReliabilityPolicy.BEST_EFFORT}
_DURABILITY = {
    interface.VOLATILE: DurabilityPolicy.VOLATILE,
    interface.TRANSIENT_LOCAL: DurabilityPolicy.TRANSIENT_LOCAL,
}


def msg_class(type_name: str) -> type:
    """The generated rclpy message class of "pkg/msg/Type" (a publisher's or subscription's type support)."""
    package, _, name = type_name.split("/")
    return getattr(importlib.import_module(f"{package}.msg"), name)


def qos_profile(spec: Endpoint | Qos, *, depth: int | None = None) -> QoSProfile:
    """The rclpy profile of a table entry (what its publisher offers); `depth` sets a
    reader's own queue with the writer's reliability and durability, so they match."""
    qos = spec.qos if isinstance(spec, Endpoint) else spec
    if qos is None:
        raise ValueError(f"{spec.name} is a service: it has no topic QoS")
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=qos.depth if depth is None else depth,
        reliability=_RELIABILITY[qos.reliability],
        durability=_DURABILITY[qos.durability],
    )


# Named profiles (tests and tools subscribe with these).
# A reader of latched topics that must see every state, not just the newest (recorders,
# test probes): it gets the stored sample on joining and queues later ones while busy.
LATCHED_LOG_QOS = qos_profile(interface.LATCHED, depth=interface.LOG_DEPTH)
EVENT_QOS = qos_profile(interface.EVENTS)
# A viewer that keeps every frame it gets while busy (the demo's GIFs), best effort as offered.
VIEWER_LOG_QOS = qos_profile(interface.VIEWER, depth=interface.LOG_DEPTH)

ECHO_CHARS = 60  # how much of a rejected input a status line quotes
STATUS_CHARS = 300  # longest status line
MAX_TRACED = 64  # places whose first traceback a node logs (there are fewer in the code)
WARNING_INTERVAL_S = 1.0  # at most one rejection warning per interval in the log
DIAGNOSTICS_PERIOD_S = 1.0  # the diagnostic_updater rate
HARDWARE_ID = "gscan_ros"  # a DiagnosticStatus's hardware_id: these nodes drive no device


def describe(text: str, *, read_only: bool = False, int_range: tuple[int, int] | None = None,
             float_range: tuple[float, float] | None = None, constraints: str = "") -> ParameterDescriptor:
    """Parameter descriptor with a description and, for numbers, the allowed range
    (`ros2 param describe` shows them; rclpy refuses a value outside the range). A float
    parameter takes integers too (`-p step_timeout:=60` and `ros2 param set ... 60` send
    one): it is dynamically typed, and `number_in` checks the value."""
    descriptor = ParameterDescriptor(description=text, read_only=read_only, additional_constraints=constraints)
    if int_range is not None:
        descriptor.integer_range = [IntegerRange(from_value=int_range[0], to_value=int_range[1], step=1)]
    if float_range is not None:
        descriptor.floating_point_range = [FloatingPointRange(from_value=float(float_range[0]),
                                                              to_value=float(float_range[1]), step=0.0)]
        descriptor.dynamic_typing = True
    return descriptor


def number_in(name: str, value: object, descriptor: ParameterDescriptor) -> float:
    """The value of a float parameter (`describe(float_range=...)`) as a float: an integer
    or a double within its range, else a GscanError naming it (rclpy checks the range of
    doubles only, and the type of none, as the parameter is dynamically typed)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise GscanError(f"parameter {name} must be a number, got {value!r}")
    (bounds,) = descriptor.floating_point_range
    if not bounds.from_value <= value <= bounds.to_value:
        raise GscanError(f"parameter {name} must lie in [{bounds.from_value:g}, {bounds.to_value:g}], got {value!r}")
    return float(value)


def validated(check: Callable[[dict[str, object]], None]) -> Callable[[list], SetParametersResult]:
    """An on-set-parameters callback from `check({name: new value})`: a GscanError,
    ValueError or OSError (a path that cannot be read or created) it raises rejects the
    whole change, its message being the reason `ros2 param set` prints. Validate there;
    apply in a post-set callback. Any other exception is a bug: it is logged with its
    traceback and the change is refused (an exception escaping the parameter service
    would end the node)."""

    def callback(parameters: list) -> SetParametersResult:
        try:
            check({p.name: p.value for p in parameters})
        except (GscanError, ValueError) as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        except OSError as exc:
            where = f"{exc.filename}: " if exc.filename else ""
            return SetParametersResult(successful=False, reason=f"{where}{exc.strerror or exc}")
        except Exception as exc:  # noqa: BLE001 - a node must survive its own bugs
            node = getattr(check, "__self__", None)  # the node whose method `check` is
            logger = node.get_logger() if isinstance(node, Node) else logging.getLogger("gscan_ros.nodes")
            logger.error(traceback.format_exc())
            return SetParametersResult(successful=False, reason=f"internal error: {type(exc).__name__}: {exc}")
        return SetParametersResult(successful=True)

    return callback


# How the parser's REJECTED report of a command begins: a client tells the parser's
# refusal of its own command from that of another client's by it.
COMMAND_REFUSAL = "rejected command"


def command_refusal(command: str) -> str:
    """The start of the parser's REJECTED report of `command`."""
    return f"{COMMAND_REFUSAL} {quote(command)}"


def quote(value: object) -> str:
    """repr() of a rejected input, shortened so a 10 kB command gives a one-line status;
    only the start of a long text is looked at, so a 50 MB one costs no more."""
    if isinstance(value, str) and len(value) > ECHO_CHARS:
        return f"{repr(value[:ECHO_CHARS])[:ECHO_CHARS]}... ({len(value)} chars)"
    text = repr(value)
    return text if len(text) <= ECHO_CHARS else f"{text[:ECHO_CHARS]}... ({len(str(value))} chars)"


def steady_timer(node: Node, period_s: float, callback: Callable[[], None]):
    """A timer on the steady clock: the node clock stops with `use_sim_time` and no /clock,
    which would stop a watchdog or the diagnostics with it."""
    return node.create_timer(period_s, callback, clock=Clock(clock_type=ClockType.STEADY_TIME))


class StatusReporter:
    """A node's health: one human-readable line per event on `status`, and its
    DiagnosticStatus on `/diagnostics` (docs/ros.md "Health").

    Lines are prefixed with the node name and capped at STATUS_CHARS, so an error that
    quotes a 10 kB input still yields one short line. Every line is published, but
    rejections and internal errors are logged as warnings/errors at most once per
    WARNING_INTERVAL_S (the others at debug level, counted in the next one): rclpy's
    logger is slow per call (docs/results.md), and a flood of bad input must not multiply that.

    The diagnostic level follows the last line: OK after an event (`info`), WARN after
    a rejected input (`reject`), ERROR after an internal error (`error`, a bug caught in
    a callback). It is published at 1 Hz, and at once when the level changes, with the
    last line as its message and the counts of rejections and errors, plus `counters()`.
    """

    def __init__(self, node: Node, counters: Callable[[], dict[str, object]] = dict) -> None:
        self._node = node
        self._counters = counters
        self._pub = node.create_publisher(String, STATUS, qos_profile(interface.STATUS))
        self._diagnostics_pub = node.create_publisher(DiagnosticArray, DIAGNOSTICS, qos_profile(interface.DIAGNOSTICS))
        self._next_warning = 0.0
        self._unlogged = 0
        self._level, self._message = DiagnosticStatus.OK, "started"
        self._rejected = self._errors = 0
        self._traced: set[tuple[str, str]] = set()  # (where, exception type) whose traceback was logged
        steady_timer(node, DIAGNOSTICS_PERIOD_S, self.publish_diagnostics)
        if node.get_parameter("use_sim_time").value:
            node.get_logger().warning("use_sim_time is ignored: the stack stamps and times with the system clock, "
                                      "the clock of the DDS source timestamps lock-step compares (docs/ros.md)")

    @property
    def level(self) -> bytes:
        """The node's diagnostic level (DiagnosticStatus.OK, WARN or ERROR)."""
        return self._level

    def info(self, text: str) -> None:
        line = self._publish(text, DiagnosticStatus.OK)
        self._node.get_logger().info(line)

    def reject(self, text: str) -> None:
        """An input the node refused: it serves on (WARN)."""
        self._rejected += 1
        self._log_throttled(self._publish(text, DiagnosticStatus.WARN), self._node.get_logger().warning)

    def error(self, text: str) -> None:
        """A bug in gscan_ros caught in a callback: the node serves on (ERROR)."""
        self._errors += 1
        self._log_throttled(self._publish(text, DiagnosticStatus.ERROR), self._node.get_logger().error)

    def internal_error(self, exc: BaseException, where: str, context: str = "") -> str:
        """A bug caught in `where`: its traceback is logged the first time it happens there
        (a bug every message hits would otherwise log one per message), and a short line,
        after `context`, goes to `status` every time (`error`). Returns that line's text."""
        key = (where, type(exc).__name__)
        if key not in self._traced and len(self._traced) < MAX_TRACED:
            self._traced.add(key)
            self._node.get_logger().error("".join(traceback.format_exception(exc)))
        text = f"{context}internal error in {where}: {type(exc).__name__}: {exc}"
        self.error(text)
        return text

    def publish_diagnostics(self) -> None:
        if not self._node.context.ok():  # shut down (Ctrl-C) before the node is destroyed
            return
        values = {"rejected inputs": self._rejected, "internal errors": self._errors, **self._counters()}
        status = DiagnosticStatus(
            level=self._level, name=self._node.get_fully_qualified_name(), message=self._message,
            hardware_id=HARDWARE_ID, values=[KeyValue(key=key, value=str(value)) for key, value in values.items()],
        )
        header = Header(stamp=time_msg(time.time_ns()))  # system time, as every stamp of the stack
        self._diagnostics_pub.publish(DiagnosticArray(header=header, status=[status]))

    def _publish(self, text: str, level: bytes) -> str:
        """Publish the line on `status` and take its level; returns the line."""
        line = self._line(text)
        if self._node.context.ok():  # after Ctrl-C the node still ends its work: the log keeps the line
            self._pub.publish(text_to_cdr(f"{self._node.get_name()}: {line}"))
        changed = level != self._level
        self._level, self._message = level, line
        if changed:
            self.publish_diagnostics()
        return line

    def _log_throttled(self, line: str, log: Callable[[str], object]) -> None:
        now = time.monotonic()
        if now < self._next_warning:
            self._unlogged += 1
            self._node.get_logger().debug(line)
            return
        more = f" (and {self._unlogged} more, see the status topic)" if self._unlogged else ""
        log(line + more)
        self._next_warning, self._unlogged = now + WARNING_INTERVAL_S, 0

    @staticmethod
    def _line(text: str) -> str:
        """One line: line breaks become spaces; spaces within a line stay, so a quoted input reads as sent."""
        line = " ".join(part.strip() for part in text.strip().splitlines())
        return line if len(line) <= STATUS_CHARS else line[: STATUS_CHARS - 3] + "..."


CallbackT = TypeVar("CallbackT", bound=Callable[..., None])


def report_failure(node: Node, exc: Exception, where: str, context: str = "") -> None:
    """Report an exception a node caught in `where` and serves on (the node has `status`).

    A `GscanError` is a rejected input: `context` and its message go to `status` (WARN).
    Anything else is a bug in gscan_ros: the traceback goes to the log and a short line to
    `status` (ERROR).
    """
    if not node.context.ok():  # Ctrl-C came while the callback ran: its publishers are gone with the context
        node.get_logger().info(f"{where} stopped by the shutdown ({type(exc).__name__}: {exc})")
        return
    if isinstance(exc, GscanError):
        node.status.reject(f"{context}{exc}")
        return
    node.status.internal_error(exc, where)


def guarded(callback: CallbackT) -> CallbackT:
    """Decorate a node callback so no input can kill the node (`report_failure`): a rejected
    input or a bug is one `status` line, and the node keeps serving the next message."""

    @functools.wraps(callback)
    def guarded_callback(self, *args, **kwargs):
        try:
            return callback(self, *args, **kwargs)
        except Exception as exc:  # noqa: BLE001 - a node must survive its own bugs
            report_failure(self, exc, callback.__name__)
        return None

    return guarded_callback  # type: ignore[return-value]


def guarded_trigger(failure: str) -> Callable[[CallbackT], CallbackT]:
    """`guarded` for a std_srvs/Trigger service: any exception becomes `success=False`.

    The response message is `<failure>: <reason>`, `status` gets the same line (a
    rejection, or an internal error for a bug), and the node keeps serving (an
    exception escaping a service callback ends the node).
    """

    def decorate(callback: CallbackT) -> CallbackT:
        @functools.wraps(callback)
        def guarded_callback(self, request, response):
            try:
                return callback(self, request, response)
            except GscanError as exc:
                response.success, response.message = False, f"{failure}: {exc}"
                self.status.reject(response.message)
            except Exception as exc:  # noqa: BLE001 - a node must survive its own bugs
                response.success = False
                response.message = self.status.internal_error(exc, callback.__name__, context=f"{failure}: ")
            return response

        return guarded_callback  # type: ignore[return-value]

    return decorate


NodeT = TypeVar("NodeT", bound=Node)


STOP_POLL_S = 0.1  # how soon a spin loop notices a stop request (a signal is handled between waits)


@contextlib.contextmanager
def stop_requests() -> "contextlib.AbstractContextManager[threading.Event]":
    """SIGINT and SIGTERM set the event it yields instead of raising KeyboardInterrupt in
    whatever callback runs, so a callback always finishes: a recorder never leaves a chunk
    half written, a world never half a step. A second signal raises KeyboardInterrupt,
    for a node stuck in a callback. Main thread only (Python's rule for signal handlers);
    rclpy must be initialised with `SignalHandlerOptions.NO`, or its own handler shuts
    the context down first and chains to the one that raises."""
    requested = threading.Event()

    def on_signal(signum, frame) -> None:
        if requested.is_set():
            raise KeyboardInterrupt
        requested.set()

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield requested
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def spin_until(executor: Executor, stop: threading.Event) -> None:
    """Spin `executor` until `stop` is set or its context shuts down."""
    while not stop.is_set() and executor.context.ok():
        executor.spin_once(timeout_sec=STOP_POLL_S)


def run(node_factory: Callable[[], NodeT], args: list[str] | None = None) -> int:
    """`main()` of a node executable: init, spin until SIGINT/SIGTERM, clean up.

    The signal ends the spin between callbacks (`stop_requests`); the node is destroyed
    while its context is still up, so what it does on the way out (a recorder's last
    reports and bag summary) is published and written.
    A configuration error (bad parameter, missing checkpoint) is one line on stderr and
    exit status 1, like the `gscan-ros` CLI.
    """
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    node = None
    try:
        with stop_requests() as stop:
            node = node_factory()
            executor = SingleThreadedExecutor()
            executor.add_node(node)
            spin_until(executor, stop)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (GscanError, ParameterException) as exc:  # a bad parameter value: one line, like the CLI
        print(f"error: {exc}", file=sys.stderr)
        return 1
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
