"""GscanCommander: drive a running gscan_ros stack by tasks, like nav2_simple_commander's BasicNavigator.

A client node for scripts, the demo, benchmarks and tests: it sends commands on
`command`, calls `reset_world`, and turns what the stack publishes into one
`EpisodeResult` per command. It holds no domain logic: the outcome is the one the
policy (or the parser, for a command it refuses) reports on `episode_status`, and the
episode's actions are those the policy published between its ACTIVE report and its end
(docs/ros.md "Episodes"), so it needs no node names and works under renames.

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
from actionlib_msgs.msg import GoalStatus
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import Image
from std_msgs.msg import String
from std_srvs.srv import Trigger

from gscan_ros import episode_status as es
from gscan_ros import interface
from gscan_ros.errors import GscanError
from gscan_ros.language.graph import CommandGraph
from gscan_ros.nodes.common import (
    ACTION,
    COMMAND,
    COMMAND_GRAPH,
    COMMAND_REFUSAL,
    EPISODE_STATUS,
    OBSERVATION,
    RESET_WORLD,
    STATUS,
    VIEWER_LOG_QOS,
    attention_topic,
    command_refusal,
    qos_profile,
)
from gscan_ros.world.types import Action
from msg_adapters import cdr_to_action, cdr_to_episode_status, cdr_to_graph, cdr_to_text, text_to_cdr

READY_TIMEOUT_S = 60.0
# DDS matches the two ends of a topic apart: the commander's subscriptions can count a
# publisher before that publisher has matched them (and sends them nothing). Once the stack
# looks ready, the commander spins this long more, the first time, for the far ends to match.
MATCH_SETTLE_S = 0.5
# After the end report: how long to wait for the episode's last actions and its graph
# (topics are not ordered with each other).
LATE_GRACE_S = 5.0
# An ending without <eos> (preempted, rejected) marks no last action: its actions are in once
# the action topic has been quiet this long after the end report.
QUIET_S = 0.3
POLL_S = 0.02
# Topics the stack must be listening on before a command is sent (`wait_until_ready`).
STACK_INPUTS = (COMMAND, COMMAND_GRAPH, OBSERVATION, ACTION)
# Topics whose stack publishers the commander must be matched with by then: an episode can
# end before a late subscription matches, and these say what it did.
STACK_OUTPUTS = (COMMAND_GRAPH, EPISODE_STATUS, ACTION, STATUS)


class Outcome(enum.StrEnum):
    """How an episode ended, as the stack reported it."""

    SUCCEEDED = "succeeded"  # the policy ended it with its own <eos>
    MAX_STEPS = "max_steps"  # the policy forced <eos>: at max_steps, after a failed step or at step_timeout
    PREEMPTED = "preempted"  # another command or a world reset replaced it (`reason` says which)
    REJECTED = "rejected"  # the parser (or the policy) refused the command
    TIMEOUT = "timeout"  # no end within the timeout


# The policy's reported outcomes, as the commander names them.
OUTCOMES = {es.COMPLETE: Outcome.SUCCEEDED, es.CUT: Outcome.MAX_STEPS, es.PREEMPTED: Outcome.PREEMPTED,
            es.REJECTED: Outcome.REJECTED}


@dataclass
class EpisodeResult:
    """One command's episode, as seen from outside the stack."""

    command: str  # the text sent
    outcome: Outcome
    actions: list[Action] = field(default_factory=list)  # as received; the closing <eos> included when it came
    graph: CommandGraph | None = None  # what the parser understood (canonical command, typed text)
    elapsed: float = 0.0  # seconds from sending the command to the end
    status: list[str] = field(default_factory=list)  # every status line received meanwhile
    reason: str = ""  # the end report's text: why it was rejected, cut or preempted
    episode_id: str = ""  # the policy's id of the episode (its `episode_status` goal id)
    sent_ns: int = 0  # wall clock when the command was published
    action_times_ns: list[int] = field(default_factory=list)  # when each action was received (DDS)
    # word -> serialized mono8 maps (msg_adapters.cdr_to_attention), for watched words
    attention: dict[str, list[bytes]] = field(default_factory=dict)

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
        self._last_action_at = 0.0  # monotonic time the latest action came
        self._graphs: list[tuple[int, bytes]] = []  # (source ns, serialized graph) since the last send
        self._reports: list[tuple[int, es.EpisodeStatus]] = []  # (source ns, report) since the last send
        self._attention: dict[str, list[tuple[int, bytes]]] = {}
        self._command_pub = self.create_publisher(String, COMMAND, qos_profile(interface.COMMAND))
        self._reset_client = self.create_client(Trigger, RESET_WORLD)
        self._matched = False  # MATCH_SETTLE_S spun once the stack looked ready
        self._outputs = {
            ACTION: self.create_subscription(String, ACTION, self._on_action, qos_profile(interface.ACTION), raw=True),
            STATUS: self.create_subscription(String, STATUS, self._on_status, qos_profile(interface.STATUS), raw=True),
            EPISODE_STATUS: self.create_subscription(GoalStatus, EPISODE_STATUS, self._on_report,
                                                     qos_profile(interface.EPISODE_STATUS), raw=True),
            COMMAND_GRAPH: self.create_subscription(String, COMMAND_GRAPH, self._on_graph,
                                                    qos_profile(interface.COMMAND_GRAPH, depth=interface.LOG_DEPTH),
                                                    raw=True),
        }
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
                self.create_subscription(Image, attention_topic(word), self._attention_sink(word), VIEWER_LOG_QOS,
                                         raw=True)

    def _attention_sink(self, word: str) -> Callable:
        return lambda data, info: self._attention[word].append((info["source_timestamp"], data))

    def _on_action(self, data: bytes, info: dict) -> None:
        try:
            action = cdr_to_action(data)
        except GscanError:
            return  # not an action; the world simulator reports it
        self._actions.append((info["source_timestamp"], info["received_timestamp"], action))
        self._last_action_at = time.monotonic()

    def _on_status(self, data: bytes) -> None:
        try:
            self.status_log.append(cdr_to_text(data))
        except GscanError:
            return  # not a serialized String

    def _on_graph(self, data: bytes, info: dict) -> None:
        self._graphs.append((info["source_timestamp"], data))

    def _on_report(self, data: bytes, info: dict) -> None:
        try:
            self._reports.append((info["source_timestamp"], cdr_to_episode_status(data)))
        except GscanError:
            return  # not a report of the stack's

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
        """Wait until something listens on the stack's inputs (command, command graph,
        observation, action), `reset_world` is served and the commander hears the stack's
        outputs (command graph, episode status, action, status): a command sent now is parsed,
        followed and executed, and what happens is heard. Any node names do: renamed or
        namespaced stacks too."""
        me = self.get_name()

        def ready() -> bool:
            for topic in STACK_INPUTS:
                infos = self.get_subscriptions_info_by_topic(self.resolve_topic_name(topic))
                if not any(i.node_name != me for i in infos):
                    return False
            if not all(self._outputs[topic].get_publisher_count() > 0 for topic in STACK_OUTPUTS):
                return False
            return self._reset_client.service_is_ready()

        self.spin_until(ready, timeout, "the gscan_ros stack (subscribers on command, command_graph, observation, "
                                        "action, publishers of command_graph, episode_status, action, status "
                                        "and the reset_world service)")
        if not self._matched:
            self.spin_for(MATCH_SETTLE_S)
            self._matched = True

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
        self._reports.clear()
        for maps in self._attention.values():
            maps.clear()
        sent_ns = time.time_ns()
        self._command_pub.publish(text_to_cdr(text))
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
        episode: tuple[int, es.EpisodeStatus] | None = None  # (source ns, report) of its start
        end: tuple[int, es.EpisodeStatus] | None = None
        while end is None and time.monotonic() < deadline:
            episode, end = _episode_reports(self._reports, sent_ns, command, self._graph_of(command, sent_ns))
            if end is None:
                self._executor.spin_once(timeout_sec=POLL_S)
        if end is not None and episode is not None:  # its last actions and graph may still be on their way
            ended_at = time.monotonic()
            grace = min(deadline, ended_at + LATE_GRACE_S)
            while time.monotonic() < grace and not self._settled(command, sent_ns, episode[0], end, ended_at,
                                                                 status_from):
                self._executor.spin_once(timeout_sec=POLL_S)
        start_ns = episode[0] if episode is not None else sent_ns
        end_ns = end[0] if end is not None else time.time_ns()
        actions = [item for item in self._actions if start_ns < item[0] <= end_ns]
        graph = self._graph_of(command, sent_ns)
        return EpisodeResult(
            command=command,
            outcome=OUTCOMES[end[1].outcome] if end is not None else Outcome.TIMEOUT,
            actions=[a for _, _, a in actions],
            graph=graph[1] if graph is not None else None,
            elapsed=time.monotonic() - started,
            status=list(self.status_log[status_from:]),
            reason=end[1].text if end is not None else "",
            episode_id=(episode or end)[1].episode_id if (episode or end) else "",
            sent_ns=sent_ns,
            action_times_ns=[received for _, received, _ in actions],
            attention={word: [m for t, m in maps if t >= sent_ns] for word, maps in self._attention.items()},
        )

    def _settled(self, command: str, sent_ns: int, start_ns: int, end: tuple[int, es.EpisodeStatus],
                 ended_at: float, status_from: int) -> bool:
        """Everything about the ended episode has arrived: the command's graph, the policy's
        `status` line of the end (published just after the report, on another topic), and its
        last action: the `<eos>` when it ended with one (the policy's actions arrive in order),
        else whatever came before the action topic fell quiet for QUIET_S after the end report."""
        if self._graph_of(command, sent_ns) is None:
            return False
        told = f"episode {end[1].episode_id} {end[1].outcome}:"
        if not any(told in line for line in self.status_log[status_from:]):
            return False
        if end[1].outcome not in (es.COMPLETE, es.CUT):
            return time.monotonic() - max(ended_at, self._last_action_at) >= QUIET_S
        return any(start_ns < t <= end[0] and a is Action.EOS for t, _, a in self._actions)

    def _graph_of(self, command: str, sent_ns: int) -> tuple[int, CommandGraph] | None:
        """(source ns, graph) the parser made of `command`: the first valid graph published
        after it was sent that was typed as `command` (another client's command may be parsed
        in between), else the first valid one."""
        first = None
        for t_ns, data in self._graphs:
            if t_ns < sent_ns:
                continue
            try:
                graph = cdr_to_graph(data)
            except GscanError:
                continue
            if (graph.typed or graph.command) == command:
                return t_ns, graph
            first = first or (t_ns, graph)
        return first

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


def _episode_reports(reports: list[tuple[int, es.EpisodeStatus]], sent_ns: int, command: str,
                     graph: tuple[int, CommandGraph] | None):
    """(start, end) reports of the episode `command`, sent at `sent_ns`, began; each may still
    be None. The parser's refusal names the command; otherwise the episode is the first one
    started after its graph was published whose ACTIVE text is the graph's command, or the
    policy's refusal of that graph (a REJECTED report of an episode that never started)."""
    refused = command_refusal(command)
    started: set[str] = set()
    episode = None
    for t_ns, report in reports:
        if t_ns < sent_ns:
            continue
        if report.outcome == es.REJECTED and report.episode_id not in started and report.text.startswith(refused):
            return None, (t_ns, report)
        if episode is None:
            if graph is None or t_ns < graph[0]:
                started.add(report.episode_id)
            elif report.outcome == es.ACTIVE and report.text == graph[1].command:
                episode = (t_ns, report)
            elif (report.outcome == es.REJECTED and report.episode_id not in started
                  and not report.text.startswith(COMMAND_REFUSAL)):  # not the parser's of another command
                return None, (t_ns, report)
            started.add(report.episode_id)
        elif report.episode_id == episode[1].episode_id and report.ended:
            return episode, (t_ns, report)
    return episode, None
