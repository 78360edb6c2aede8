"""GscanCommander: drive a running gscan_ros stack by tasks, like nav2_simple_commander's BasicNavigator.

A client node for scripts, the demo, benchmarks and tests: it sends commands on
`command`, calls `reset_world`, and turns what the stack publishes (`action`, `status`,
`command_graph`, attention maps) into one `EpisodeResult` per command. It holds no
domain logic: the outcome is read from the nodes' own status lines (docs/ros.md).

    rclpy.init()
    commander = GscanCommander()
    commander.wait_until_ready()
    result = commander.run_episode("walk to a red circle", timeout=60)
    print(result.outcome, [a.token for a in result.actions])
    commander.reset_world()
    commander.shutdown()

The commander spins itself (its own executor, in the calling thread) while it waits,
so it also works beside a stack that another executor spins in the same process.
"""
from __future__ import annotations

import enum
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import Image
from std_msgs.msg import String
from std_srvs.srv import Trigger

from gscan_ros import interface
from gscan_ros.errors import GscanError
from gscan_ros.language.graph import CommandGraph
from gscan_ros.nodes.common import (
    ACTION,
    COMMAND,
    COMMAND_GRAPH,
    OBSERVATION,
    RESET_WORLD,
    STATUS,
    VIEWER_LOG_QOS,
    StatusReporter,
    attention_topic,
    qos_profile,
    quote,
)
from gscan_ros.world.types import Action
from msg_adapters import msg_to_action, msg_to_graph

READY_TIMEOUT_S = 60.0
EOS_GRACE_S = 5.0  # after <eos>, how long to wait for the command graph and the policy's closing status line
POLL_S = 0.02
# Who listens where, by default node name (docs/ros.md): what `wait_until_ready` waits for.
STACK_SUBSCRIBERS = {
    COMMAND: "parser_node",
    COMMAND_GRAPH: "policy_node",
    OBSERVATION: "policy_node",
    ACTION: "world_simulator_node",
}


class Outcome(enum.StrEnum):
    """How an episode ended, as the stack reported it."""

    SUCCEEDED = "succeeded"  # the policy ended it with its own <eos>
    MAX_STEPS = "max_steps"  # the policy forced <eos> after max_steps actions
    ABORTED = "aborted"  # a world reset ended it (no <eos>)
    PREEMPTED = "preempted"  # another command replaced it
    REJECTED = "rejected"  # the parser (or the policy) refused the command
    TIMEOUT = "timeout"  # no end within the timeout


@dataclass
class EpisodeResult:
    """One command's episode, as seen from outside the stack."""

    command: str  # the text sent
    outcome: Outcome
    actions: list[Action] = field(default_factory=list)  # as received; the closing <eos> included when it came
    graph: CommandGraph | None = None  # what the parser understood (canonical command, typed text)
    elapsed: float = 0.0  # seconds from sending the command to the end
    status: list[str] = field(default_factory=list)  # every status line received meanwhile
    reason: str = ""  # the status line that decided a rejection, abort or preemption
    sent_ns: int = 0  # wall clock when the command was published
    action_times_ns: list[int] = field(default_factory=list)  # when each action was received (DDS)
    attention: dict[str, list[Image]] = field(default_factory=dict)  # word -> mono8 maps, for watched words

    @property
    def steps(self) -> int:
        """Actions taken in the world (the closing <eos> is not one)."""
        return sum(a is not Action.EOS for a in self.actions)

    @property
    def moves(self) -> list[Action]:
        return [a for a in self.actions if a is not Action.EOS]

    @property
    def succeeded(self) -> bool:
        return self.outcome is Outcome.SUCCEEDED

    @property
    def finished(self) -> bool:
        """Ended with an <eos> (the model's own or forced by max_steps)."""
        return self.outcome in (Outcome.SUCCEEDED, Outcome.MAX_STEPS)


class GscanCommander(Node):
    """Task-level client of a gscan_ros stack (see the module docstring).

    Construct it like any node in an initialised context (`context=None`: rclpy's
    default), or with `GscanCommander.connect()`, which makes and owns a context.
    `attention_words` (or `watch_attention`) subscribes to those words' attention maps;
    each EpisodeResult then carries the maps received during its episode.
    """

    def __init__(self, node_name: str = "gscan_commander", namespace: str = "", *, context=None,
                 attention_words: Iterable[str] = ()) -> None:
        super().__init__(node_name, namespace=namespace, context=context)
        self._own_context = None
        self._executor = SingleThreadedExecutor(context=self.context)
        self._executor.add_node(self)
        self.status_log: list[str] = []  # every status line since the commander started
        self._actions: list[tuple[int, int, Action]] = []  # (source ns, received ns, action) since the last send
        self._graphs: list[tuple[int, String]] = []  # (source ns, msg) since the last send
        self._attention: dict[str, list[tuple[int, Image]]] = {}
        self._command_pub = self.create_publisher(String, COMMAND, qos_profile(interface.COMMAND))
        self._reset_client = self.create_client(Trigger, RESET_WORLD)
        self.create_subscription(String, ACTION, self._on_action, qos_profile(interface.ACTION))
        self.create_subscription(String, STATUS, self._on_status, qos_profile(interface.STATUS))
        self.create_subscription(String, COMMAND_GRAPH, self._on_graph,
                                 qos_profile(interface.COMMAND_GRAPH, depth=interface.LOG_DEPTH))
        self.watch_attention(attention_words)

    @classmethod
    def connect(cls, domain_id: int | None = None, **kwargs) -> "GscanCommander":
        """A commander in a context of its own (ROS_DOMAIN_ID, or `domain_id`); `shutdown()` ends both."""
        context = rclpy.Context()
        rclpy.init(context=context, domain_id=domain_id)
        try:
            commander = cls(context=context, **kwargs)
        except BaseException:
            rclpy.try_shutdown(context=context)
            raise
        commander._own_context = context
        return commander

    # -- subscriptions -----------------------------------------------------------------
    def watch_attention(self, words: Iterable[str]) -> None:
        """Collect the attention maps of `words` (best effort, as the policy offers them)."""
        for word in words:
            if word not in self._attention:
                self._attention[word] = []
                self.create_subscription(Image, attention_topic(word), self._attention_sink(word), VIEWER_LOG_QOS)

    def _attention_sink(self, word: str) -> Callable:
        return lambda msg, info: self._attention[word].append((info["source_timestamp"], msg))

    def _on_action(self, msg: String, info: dict) -> None:
        try:
            action = msg_to_action(msg)
        except GscanError:
            return  # not an action; the world simulator reports it
        self._actions.append((info["source_timestamp"], info["received_timestamp"], action))

    def _on_status(self, msg: String) -> None:
        self.status_log.append(msg.data)

    def _on_graph(self, msg: String, info: dict) -> None:
        self._graphs.append((info["source_timestamp"], msg))

    # -- waiting -----------------------------------------------------------------------
    def spin_until(self, condition: Callable[[], bool], timeout: float, what: str) -> None:
        """Spin until `condition()` holds; GscanError after `timeout` seconds."""
        deadline = time.monotonic() + timeout
        while not condition():
            if time.monotonic() > deadline:
                raise GscanError(f"timed out after {timeout:.0f} s waiting for {what}")
            self._executor.spin_once(timeout_sec=POLL_S)

    def spin_for(self, seconds: float) -> None:
        """Serve the subscriptions for `seconds` (e.g. while pacing a publisher)."""
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            self._executor.spin_once(timeout_sec=min(left, POLL_S))

    def wait_until_ready(self, timeout: float = READY_TIMEOUT_S) -> None:
        """Wait until the parser, policy and world simulator are connected and `reset_world`
        is served: a command sent now is parsed, followed and executed."""
        def ready() -> bool:
            for topic, node in STACK_SUBSCRIBERS.items():
                infos = self.get_subscriptions_info_by_topic(self.resolve_topic_name(topic))
                if node not in {i.node_name for i in infos}:
                    return False
            return self._command_pub.get_subscription_count() > 0 and self._reset_client.service_is_ready()

        self.spin_until(ready, timeout, "the gscan_ros stack (parser_node, policy_node, world_simulator_node)")

    def wait_for_status(self, prefix: str, timeout: float) -> str:
        """The first status line (since the commander started) that starts with `prefix`."""
        found: list[str] = []

        def seen() -> bool:
            found[:] = [line for line in self.status_log if line.startswith(prefix)][:1]
            return bool(found)

        self.spin_until(seen, timeout, f"a status line {prefix!r}")
        return found[0]

    # -- tasks -------------------------------------------------------------------------
    def send_command(self, text: str, timeout: float = READY_TIMEOUT_S) -> int:
        """Publish `text` on `command` (once the parser subscribes); returns when it was sent (ns).

        Starts a new episode record: actions, graphs and maps from before are forgotten.
        """
        if self._command_pub.get_subscription_count() == 0:
            self.spin_until(lambda: self._command_pub.get_subscription_count() > 0, timeout,
                            "a subscriber on 'command' (parser_node)")
        self._actions.clear()
        self._graphs.clear()
        for maps in self._attention.values():
            maps.clear()
        sent_ns = time.time_ns()
        self._command_pub.publish(String(data=text))
        return sent_ns

    def reset_world(self, timeout: float = 30.0) -> str:
        """Call `reset_world`: the world loads its next situation. Returns the world's one-line
        description; GscanError when the service is missing, silent or refuses."""
        if not self._reset_client.service_is_ready():
            self.spin_until(self._reset_client.service_is_ready, timeout, "the reset_world service")
        future = self._reset_client.call_async(Trigger.Request())
        self.spin_until(future.done, timeout, "the answer of reset_world")
        response = future.result()
        if not response.success:
            raise GscanError(f"reset_world failed: {response.message}")
        return response.message

    def run_episode(self, command: str, timeout: float = 120.0) -> EpisodeResult:
        """Send `command` and wait for its episode to end (see `Outcome`); never raises on the
        episode's outcome, only when the parser never subscribes."""
        status_from = len(self.status_log)
        sent_ns = self.send_command(command, timeout)
        started = time.monotonic()
        deadline = started + timeout
        watch = _EpisodeWatch(command)
        while True:
            decided = watch.update(self._graph(sent_ns), self.status_log[status_from:], self._episode_actions(sent_ns))
            if decided is not None:
                break
            if time.monotonic() > deadline:
                decided = (Outcome.TIMEOUT, "")
                break
            self._executor.spin_once(timeout_sec=POLL_S)
        outcome, reason = decided
        if watch.eos_seen:  # the policy's closing line says whether max_steps forced the <eos>
            # The graph may still be on its way too: topics are not ordered with each other,
            # so a busy machine can deliver the <eos> action before the command graph.
            grace = min(deadline, time.monotonic() + EOS_GRACE_S)
            while time.monotonic() < grace:
                watch.see(self._graph(sent_ns))
                if watch.closed(self.status_log[status_from:]):
                    break
                self._executor.spin_once(timeout_sec=POLL_S)
            outcome = Outcome.MAX_STEPS if watch.forced(self.status_log[status_from:]) else Outcome.SUCCEEDED
        actions = self._episode_actions(sent_ns)
        return EpisodeResult(
            command=command,
            outcome=outcome,
            actions=[a for _, _, a in actions],
            graph=self._graph(sent_ns),
            elapsed=time.monotonic() - started,
            status=list(self.status_log[status_from:]),
            reason=reason,
            sent_ns=sent_ns,
            action_times_ns=[received for _, received, _ in actions],
            attention={word: [m for t, m in maps if t >= sent_ns] for word, maps in self._attention.items()},
        )

    def _episode_actions(self, sent_ns: int) -> list[tuple[int, int, Action]]:
        """Actions sent after the command, up to and including the first <eos>."""
        out = []
        for item in self._actions:
            if item[0] >= sent_ns:
                out.append(item)
                if item[2] is Action.EOS:
                    break
        return out

    def _graph(self, sent_ns: int) -> CommandGraph | None:
        """The first valid command graph published after the command was sent."""
        for t_ns, msg in self._graphs:
            if t_ns >= sent_ns:
                try:
                    return msg_to_graph(msg)
                except GscanError:
                    continue
        return None

    # -- lifecycle ---------------------------------------------------------------------
    def shutdown(self) -> None:
        """Destroy the node (and the context it owns); safe to call twice."""
        if self._executor is None:
            return
        self._executor.shutdown()
        self._executor = None
        self.destroy_node()
        if self._own_context is not None:
            rclpy.try_shutdown(context=self._own_context)
            self._own_context = None

    def __enter__(self) -> "GscanCommander":
        return self

    def __exit__(self, *exc_info) -> None:
        self.shutdown()


class _EpisodeWatch:
    """Reads one command's fate from the status lines of the parser and the policy (docs/ros.md)."""

    def __init__(self, command: str) -> None:
        # parser_node: rejected command '<quoted text>': <reason>  (quoted and spaced as StatusReporter does)
        self._rejected = "parser_node: " + StatusReporter._line(f"rejected command {quote(command)}")
        self._canonical: str | None = None
        self.eos_seen = False

    def update(self, graph: CommandGraph | None, lines: list[str], actions: list) -> tuple[Outcome, str] | None:
        """The outcome once it is known (a provisional SUCCEEDED at <eos>), else None."""
        self.see(graph)
        following = False  # the policy started this episode (lines before it are about an older one)
        for line in lines:
            if line.startswith(self._rejected):
                return Outcome.REJECTED, line
            if self._canonical is None:
                continue
            if line.startswith(f"policy_node: following {self._canonical}"):
                following = True
            elif not following:
                if line.startswith("policy_node: rejected command graph"):
                    return Outcome.REJECTED, line
            elif line.startswith(f"policy_node: aborted {self._canonical}"):
                return Outcome.ABORTED, line
            elif line.startswith(f"policy_node: preempted {self._canonical}"):
                return Outcome.PREEMPTED, line
        if actions and actions[-1][2] is Action.EOS:
            self.eos_seen = True
            return Outcome.SUCCEEDED, ""
        return None

    def see(self, graph: CommandGraph | None) -> None:
        """Note the parser's graph of the command (its canonical text names the episode)."""
        if graph is not None:
            self._canonical = repr(graph.command)

    def closed(self, lines: list[str]) -> bool:
        """The parser's graph and the policy's `done with '<command>'` line have both arrived."""
        return self._canonical is not None and any(
            line.startswith(f"policy_node: done with {self._canonical}") for line in lines)

    def forced(self, lines: list[str]) -> bool:
        """The policy reported stopping the command at max_steps."""
        marker = f"policy_node: {self._canonical} stopped at max_steps=" if self._canonical else None
        return any(line.startswith(marker) if marker else " stopped at max_steps=" in line for line in lines)
