"""policy_node: follows every command graph in lock-step with the world simulator.

Episode protocol (docs/ros.md "Lock-step"):
- a new `command_graph` resets the model's module states and starts an episode; one
  still running is preempted. Graphs that come while the node is busy are queued and
  taken in order. Every graph the node receives is reported on `episode_status`
  (actionlib_msgs/GoalStatus): ACTIVE before its first action, then how it ended
  (SUCCEEDED: the model's `<eos>`; ABORTED: an `<eos>` the node forced, at `max_steps`,
  after a failed step, or when no observation came within `step_timeout`; PREEMPTED: a
  new command or a world reset; REJECTED: a graph it cannot follow), after its last
  action, so the actions published between the two are exactly the episode's
  (docs/ros.md "Episodes"). A command is an instruction for the moment it is given: a
  graph published before the world's last reset is REJECTED, and one published before
  this node started (the latched copy a restarted policy receives, an answered command
  or one sent while no policy ran) is ignored with a line on `status`, no episode;
- the policy acts on the newest observation, publishes action t, and then acts only
  on an observation *published after* action t. "After" compares the observation's
  DDS source timestamp with the time action t was sent, so a reply that was already
  in flight, or a latched copy, is never mistaken for the result of action t (the
  clocks of the two hosts must agree; `step_timeout` ends an episode that waits in vain);
- the episode ends with `<eos>`, the model's or one the node forces, or is preempted by
  a world reset (`world_reset`, whose DDS source timestamp R is the reset's time): the
  policy sends nothing more for it, and ignores observations, graphs and replies
  published before R.
Each step also publishes every word module's attention map on `attention/<word>` and, for
a command with a size word, the size-ordering map on `attention/size_ordering`, each with
the header (stamp, grid frame) of the observation it was computed from. These are for
viewers: a map that cannot be published is reported on `status` and the episode goes on.
"""
from __future__ import annotations

import time

import numpy as np
from actionlib_msgs.msg import GoalStatus
from rclpy.duration import Duration
from rclpy.node import Node
from sensor_msgs.msg import Image
from std_msgs.msg import Header, String

from gscan_ros import episode_status as es
from gscan_ros import interface
from gscan_ros.analysis.explain import size_ordering
from gscan_ros.errors import GscanError
from gscan_ros.language.graph import CommandGraph
from gscan_ros.model.policy import MAX_STEPS
from gscan_ros.nodes.common import (
    ACTION,
    COMMAND_GRAPH,
    EPISODE_STATUS,
    OBSERVATION,
    SIZE_ORDERING,
    WORLD_RESET,
    StatusReporter,
    attention_topic,
    describe,
    guarded,
    number_in,
    qos_profile,
    report_failure,
    run,
    steady_timer,
    validated,
)
from gscan_ros.runtime import configure_torch, resolve_device
from gscan_ros.world.types import Action
from msg_adapters import (
    action_to_cdr,
    attention_to_cdr,
    cdr_to_graph,
    cdr_to_observation,
    cdr_to_reset,
    episode_status_to_cdr,
    image_header,
)

MODEL_PARAMETERS = ("checkpoint", "device")
STEP_TIMEOUT_S = 30.0  # a world step takes milliseconds; a robot's gSCAN action a few seconds
WATCHDOG_PERIOD_S = 0.1  # how often a waiting episode's `step_timeout` is checked
SHUTDOWN_ACK_S = 2.0  # how long a stopping node waits for its last episode report to be taken


class PolicyNode(Node):
    def __init__(self, policy=None, **kwargs) -> None:
        """`policy`: an already loaded Policy (tests); default: load `checkpoint`."""
        super().__init__("policy_node", **kwargs)
        self.declare_parameter(
            "checkpoint", "", describe("policy checkpoint (.pt); empty: the model shipped with gscan_ros (a change "
                                       "loads it, for the next command; a bad one is refused)")
        )
        self.declare_parameter(
            "max_steps", MAX_STEPS, describe("actions per episode before <eos> is forced (read at each episode start)",
                                       int_range=(1, 100_000))
        )
        self._step_timeout_descriptor = describe(
            "seconds an episode waits for an observation published after its last action (or, at its start, "
            "for a first one) before <eos> is forced and it ends ABORTED; 0: wait forever (a change applies "
            "at once)", float_range=(0.0, 86_400.0))
        self.declare_parameter("step_timeout", STEP_TIMEOUT_S, self._step_timeout_descriptor)
        self._seconds(self.get_parameter("step_timeout").value)  # a bad override fails the start
        self.declare_parameter(
            "attention_upsample", 10, describe("pixels per grid cell in attention/<word> images", int_range=(1, 100))
        )
        self.declare_parameter(
            "torch_threads", 1, describe("CPU threads for the model; one is fastest for single-step inference "
                                         "(0: torch's default)", int_range=(0, 1024))
        )
        self.declare_parameter(
            "device", "cpu", describe("where the model runs: cpu, cuda, or auto (cuda if torch sees a GPU); a change "
                                      "reloads the model", constraints="one of: cpu, cuda, auto")
        )
        self.status = StatusReporter(self, counters=lambda: {"episodes": self._episodes})
        configure_torch(self.get_parameter("torch_threads").value)
        self._policy = policy if policy is not None else self._load_policy({})
        self._candidate = None  # loaded while a checkpoint/device change is checked
        self._next_policy = None  # the accepted change's model, taken at the next command
        self._action_pub = self.create_publisher(String, ACTION, qos_profile(interface.ACTION))
        self._episode_pub = self.create_publisher(GoalStatus, EPISODE_STATUS, qos_profile(interface.EPISODE_STATUS))
        self._episodes = 0  # episodes started or rejected: numbers their ids
        self._episode: es.EpisodeStatus | None = None  # the running episode's ACTIVE report
        self._attention_pubs: dict[str, object] = {}
        self._size_ordering_pub = None
        self._observation: np.ndarray | None = None
        self._observation_ns = 0  # DDS source timestamp of the newest observation
        self._observation_header = None  # its stamp and frame, once one came
        self._sent_ns = -1  # when the last action the world replies to (not <eos>) left this node (-1: never)
        self._lost_reply: str | None = None  # step_timeout ended an episode on this reply: no state to start from
        self._graph: CommandGraph | None = None  # the running episode's graph, None when idle
        self._graph_ns = 0  # DDS source timestamp of the running episode's graph
        self._steps = 0
        self._step_cap = 0
        self._waiting_since = 0.0  # monotonic time the running episode began to wait for an observation
        self._started_ns = time.time_ns()
        self._reset_ns = 0  # DDS source timestamp of the world's newest reset: anything published before is past
        # The world publishes world_reset before the new state; subscribing to it first
        # makes the executor take it first when both are waiting. Of the world's state only
        # the newest matters (depth 1); every command graph is queued while the node is
        # busy, so each gets its report.
        def newest(endpoint):
            return qos_profile(endpoint, depth=interface.LATEST_DEPTH)

        self.create_subscription(Header, WORLD_RESET, self.on_world_reset, newest(interface.WORLD_RESET), raw=True)
        self.create_subscription(String, COMMAND_GRAPH, self.on_graph,
                                 qos_profile(interface.COMMAND_GRAPH, depth=interface.LOG_DEPTH), raw=True)
        self.create_subscription(Image, OBSERVATION, self.on_observation, newest(interface.OBSERVATION), raw=True)
        steady_timer(self, WATCHDOG_PERIOD_S, self.check_step)
        self.add_on_set_parameters_callback(validated(self._check_parameters))
        self.add_post_set_parameters_callback(self._apply_parameters)
        self.get_logger().info(f"policy ready (parser {self._policy.parser_name})")

    @property
    def policy(self):
        """The loaded Policy (its parser and lexicon are the ones graphs must come from)."""
        return self._policy

    @property
    def step_timeout(self) -> float:
        """`step_timeout` in seconds (the parameter may hold an integer: `-p step_timeout:=60`)."""
        return self._seconds(self.get_parameter("step_timeout").value)

    def _load_policy(self, changes: dict):
        from gscan_ros.model.policy import Policy

        checkpoint = changes.get("checkpoint", self.get_parameter("checkpoint").value)
        device = changes.get("device", self.get_parameter("device").value)
        return Policy.from_checkpoint(checkpoint or None, device=resolve_device(device))

    def _check_parameters(self, changes: dict) -> None:
        """A new checkpoint or device is loaded here, so a bad one is refused with the reason."""
        self._candidate = None
        if "step_timeout" in changes:
            self._seconds(changes["step_timeout"])
        if any(name in changes for name in MODEL_PARAMETERS):
            self._candidate = self._load_policy(changes)

    @guarded
    def _apply_parameters(self, parameters: list) -> None:
        """torch_threads now; a new model at the next command (the running episode keeps its own)."""
        names = {p.name for p in parameters}
        if self._candidate is not None:
            self._next_policy, self._candidate = self._candidate, None
        if "torch_threads" in names:
            configure_torch(self.get_parameter("torch_threads").value)
        if names & set(MODEL_PARAMETERS) and self._graph is None:
            self._take_next_policy()

    def _seconds(self, value: object) -> float:
        return number_in("step_timeout", value, self._step_timeout_descriptor)

    def _take_next_policy(self) -> None:
        if self._next_policy is not None:
            self._policy, self._next_policy = self._next_policy, None
            self.status.info(f"loaded {self.get_parameter('checkpoint').value or 'the shipped model'} on "
                             f"{self.get_parameter('device').value} (parser {self._policy.parser_name})")

    @guarded
    def on_world_reset(self, data: bytes, info: dict) -> None:
        """The reset's time is when the world published it (its DDS source timestamp, the
        clock observations are judged by); the header stamp is the world's own account."""
        cdr_to_reset(data)  # bytes that hold no Header are a rejected input
        reset_ns = info["source_timestamp"]
        if reset_ns <= self._reset_ns:
            return  # this reset or a newer one was already taken
        self._reset_ns = reset_ns
        self._lost_reply = None  # the new world's state comes next
        if self._observation_ns < reset_ns:
            self._observation = None  # the old world's state
        if self._graph is not None and self._graph_ns < reset_ns:
            self._end(es.PREEMPTED, f"the world was reset after {self._steps} actions")

    @guarded
    def on_graph(self, data: bytes, info: dict) -> None:
        published_ns = info["source_timestamp"]
        try:
            graph = cdr_to_graph(data)
        except GscanError as exc:
            self._refuse(f"bad command graph: {exc}")
            return
        if published_ns < self._started_ns:  # the latched copy of a command given before: no episode
            self.status.info(f"ignored the graph of {graph.command!r}: published before this node started")
            return
        if published_ns < self._reset_ns:
            self._refuse(f"not following {graph.command!r}: its graph was published before the world was reset")
            return
        if self._graph is not None:
            self._end(es.PREEMPTED, f"a new command came after {self._steps} actions")
        if self._lost_reply is not None and self._observation_ns <= self._sent_ns:
            # The world's state is unknown (it may have taken that action): refused now, not after step_timeout.
            self._refuse(f"not following {graph.command!r}: the world never replied to {self._lost_reply} "
                         f"(step_timeout); call reset_world, or let the world publish its state, first")
            return
        self._take_next_policy()
        try:
            self._check_grid(self._observation)
        except GscanError as exc:
            self._refuse(f"not following {graph.command!r}: {exc}")
            return
        try:
            self._policy.reset(graph)
        except GscanError as exc:
            self._refuse(f"bad command graph: {exc}")
            return
        self._graph, self._graph_ns, self._steps = graph, published_ns, 0
        self._step_cap = self.get_parameter("max_steps").value
        self._waiting_since = time.monotonic()
        self._episode = self._new_episode(es.ACTIVE, graph.command)
        self._report(self._episode)
        if self._observation is not None and self._observation_ns > self._sent_ns:
            self._act()

    @guarded
    def on_observation(self, data: bytes, info: dict) -> None:
        if info["source_timestamp"] < self._reset_ns:  # a state of the old world, delivered late: no fault
            self.status.info("ignored an observation published before the world was reset")
            return
        # Kept even when it does not fit the checkpoint, so the next command is refused
        # with the reason instead of waiting for a state it can use.
        # A writable copy (the decoded view is read-only, which torch warns about).
        self._observation, self._observation_ns = cdr_to_observation(data).copy(), info["source_timestamp"]
        self._lost_reply = None
        self._observation_header = image_header(data)  # the maps computed from it show its state
        try:
            self._check_grid(self._observation)
        except GscanError as exc:
            self.status.reject(str(exc))
            if self._graph is not None:  # accepted, then unable to go on: cut like every forced end
                self._force_eos(str(exc))
            return
        if self._graph is not None and self._observation_ns > self._sent_ns:
            self._act()

    @guarded
    def check_step(self) -> None:
        """The watchdog: an episode that waited `step_timeout` for an observation it can act on
        (a lost reply, a world that is down) is ended instead of staying ACTIVE forever."""
        timeout = self.step_timeout
        if self._graph is None or not timeout or time.monotonic() - self._waiting_since < timeout:
            return
        after = f"action {self._steps - 1}" if self._steps else "the episode started"
        if self._steps and self._observation_ns <= self._sent_ns:
            self._lost_reply = f"action {self._steps - 1} of episode {self._episode.episode_id}"
        self._force_eos(f"no observation came within step_timeout={timeout:g} s after {after}")

    def _check_grid(self, observation: np.ndarray | None) -> None:
        """The policy's checkpoint must fit the world's grid (a world of another size is reported, not followed)."""
        if observation is not None:
            self._policy.require_observation(observation.shape, "the observation")

    def _new_episode(self, outcome: str, text: str) -> es.EpisodeStatus:
        self._episodes += 1
        return es.EpisodeStatus(f"{self.get_fully_qualified_name()}/{self._episodes}", time.time_ns(), outcome, text)

    def _report(self, status: es.EpisodeStatus) -> None:
        """On `episode_status` for programs, on `status` for people."""
        self._episode_pub.publish(episode_status_to_cdr(status))
        line = f"episode {status.episode_id} {status.outcome}: {status.text}"
        (self.status.reject if status.outcome == es.REJECTED else self.status.info)(line)

    def _refuse(self, text: str) -> None:
        """A graph this node does not follow: its own REJECTED report (no ACTIVE before it)."""
        self._report(self._new_episode(es.REJECTED, text))

    def _end(self, outcome: str, why: str) -> None:
        """The running episode ended (after its last action was published)."""
        episode, self._episode, self._graph = self._episode, None, None
        self._report(es.EpisodeStatus(episode.episode_id, episode.start_ns, outcome, f"{episode.text!r}: {why}"))

    def _force_eos(self, why: str) -> None:
        """End the running episode with an `<eos>` of this node's: outcome cut (GoalStatus ABORTED)."""
        self._action_pub.publish(action_to_cdr(Action.EOS))
        self._end(es.CUT, why)

    def _act(self) -> None:
        if self._steps >= self._step_cap:
            self._force_eos(f"stopped at max_steps={self._step_cap}")
            return
        try:
            out = self._policy.step(self._observation)
            action = action_to_cdr(out.action)
        except Exception as exc:  # noqa: BLE001 - a failed step ends its episode, never the node
            self._force_eos(f"step {self._steps} failed: {type(exc).__name__}: {exc}")
            report_failure(self, exc, "the policy's step", context="the policy's step failed: ")
            return
        if out.action is not Action.EOS:  # the world replies to it: act again only on a later state
            self._sent_ns = time.time_ns()
        self._action_pub.publish(action)
        try:
            self._publish_maps(out.attention, out.antonyms)
        except Exception as exc:  # noqa: BLE001 - a viewer's map must never hold up the episode
            report_failure(self, exc, "_publish_maps", context=f"attention maps of step {self._steps} not published: ")
        if out.action is Action.EOS:
            self._end(es.COMPLETE, f"done after {self._steps} actions")
        else:
            self._steps += 1
            self._waiting_since = time.monotonic()

    def _publish_maps(self, attention: dict[str, np.ndarray], antonyms: dict[str, np.ndarray]) -> None:
        upsample = self.get_parameter("attention_upsample").value
        for word, weights in attention.items():
            pub = self._attention_pubs.get(word)
            if pub is None:
                pub = self._attention_pubs[word] = self.create_publisher(
                    Image, attention_topic(word), qos_profile(interface.ATTENTION))
            pub.publish(attention_to_cdr(weights, upsample=upsample, header=self._observation_header))
        ordering = size_ordering(attention, antonyms)
        if ordering is not None:
            self._publish_size_ordering(ordering, upsample)

    def _publish_size_ordering(self, ordering: np.ndarray, upsample: int) -> None:
        """Shifted to start at 0, so the smallest object is darkest and the biggest lightest."""
        if self._size_ordering_pub is None:
            self._size_ordering_pub = self.create_publisher(Image, SIZE_ORDERING, qos_profile(interface.SIZE_ORDERING))
        self._size_ordering_pub.publish(attention_to_cdr(ordering - ordering.min(), upsample=upsample,
                                                         header=self._observation_header))

    def destroy_node(self) -> None:
        """An episode still running ends here, PREEMPTED, so no client or recorder waits
        for its end in vain; the report is acknowledged (or `SHUTDOWN_ACK_S` passes)
        before its publisher goes. A context already shut down can carry nothing."""
        if self._graph is not None and self.context.ok():
            self._end(es.PREEMPTED, f"the policy stopped after {self._steps} actions")
            self._episode_pub.wait_for_all_acked(Duration(seconds=SHUTDOWN_ACK_S))
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run(PolicyNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
