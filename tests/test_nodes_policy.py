"""policy_node in-process with a scripted policy: lock-step timing, max_steps, preemption, bad graphs."""
import itertools
import os
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from rclpy.qos import ReliabilityPolicy
from sensor_msgs.msg import Image
from std_msgs.msg import String

from gscan_ros import interface, runtime
from gscan_ros.errors import GscanError
from gscan_ros.language import get_parser
from gscan_ros.language.lexicon import Lexicon
from gscan_ros.model.checkpoint import build_model, checkpoint_dict, save_checkpoint
from gscan_ros.model.decoder import command_vocabulary
from gscan_ros.model.policy import MAX_STEPS, StepOutput
from gscan_ros.nodes.common import EVENT_QOS, VIEWER_LOG_QOS, qos_profile
from gscan_ros.nodes.policy_node import PolicyNode
from gscan_ros.world.types import Action
from msg_adapters import (
    cdr_to_attention,
    cdr_to_episode_status,
    cdr_to_msg,
    cdr_to_text,
    graph_to_cdr,
    grid_header,
    observation_to_cdr,
    reset_to_cdr,
    text_to_cdr,
    time_ns,
)

from ros_helpers import Probe, ScriptedPolicy, fresh_domain_id, parameters, source_info

PARSER = get_parser("semantic")
_TESTS = itertools.count()


@pytest.fixture
def probe():
    """The probe in a namespace of this test's own, where the node under test is created too: a
    world simulator of an earlier test still leaving the shared domain cannot serve it a
    latched observation of its own."""
    p = Probe(fresh_domain_id(), namespace=f"/policy_test_{os.getpid()}_{next(_TESTS)}")
    yield p
    p.close()


def start(probe, script, **params):
    policy = ScriptedPolicy(script)
    node = PolicyNode(policy, context=probe.context, namespace=probe.namespace,
                      parameter_overrides=parameters(**params))
    probe.executor.add_node(node)
    return node, policy


def graph(command="walk to a red circle while spinning"):
    return graph_to_cdr(PARSER.parse(command))


def observation(value=0, header=None):
    obs = np.zeros((6, 6, 16), dtype=np.uint8)
    obs[value % 6, value // 6 % 6, 11] = 1
    return observation_to_cdr(obs, header=header)


def test_acts_only_on_observations_published_after_its_last_action(probe):
    actions = probe.record("action", String, EVENT_QOS)
    node, policy = start(probe, [Action.WALK])
    node.on_graph(graph(), source_info())
    assert policy.seen == []  # no observation yet
    node.on_observation(observation(0), source_info())
    assert len(policy.seen) == 1
    node.on_observation(observation(1), source_info(t_ns=5))  # older than action 0: in flight or latched
    assert len(policy.seen) == 1
    node.on_observation(observation(2), source_info())
    assert len(policy.seen) == 2 and policy.seen[1][2, 0, 11] == 1
    probe.spin_until(lambda: len(actions) == 2, what="two actions")
    assert [a.data for a in actions] == ["walk", "walk"]


def test_a_graph_published_before_the_node_started_is_not_followed(probe):
    node, policy = start(probe, [Action.WALK])
    node.on_observation(observation(0), source_info())
    node.on_graph(graph(), source_info(t_ns=1))
    assert policy.resets == [] and policy.seen == []


def test_acts_at_once_on_a_fresh_observation_received_before_the_graph(probe):
    node, policy = start(probe, [Action.STAY])
    node.on_observation(observation(0), source_info())
    assert policy.seen == []  # idle without a command
    node.on_graph(graph(), source_info())
    assert len(policy.seen) == 1


def test_max_steps_forces_eos(probe):
    actions = probe.record("action", String, EVENT_QOS)
    status = probe.record("status", String, EVENT_QOS)
    node, policy = start(probe, [Action.WALK], max_steps=3)
    node.on_graph(graph(), source_info())
    for _ in range(6):
        node.on_observation(observation(), source_info())
    probe.spin_until(lambda: len(actions) == 4, what="3 walks and <eos>")
    assert [a.data for a in actions] == ["walk"] * 3 + ["<eos>"]
    assert len(policy.seen) == 3  # idle after <eos>
    probe.spin_until(lambda: any("stopped at max_steps=3" in s.data for s in status), what="the cap notice")


@pytest.mark.parametrize("kind", ["seq2seq", "auxloss", "lcgn"])
def test_the_comparison_systems_drive_the_node_from_their_checkpoint(probe, tmp_path, kind):
    """The baselines need only what the node has, the command and the observation: a
    checkpoint of each kind, named by the `checkpoint` parameter, follows a command."""
    torch.manual_seed(0)
    model = build_model(kind, {}, {"tokens": command_vocabulary()})
    path = tmp_path / f"{kind}.pt"
    save_checkpoint(path, checkpoint_dict(model, parser="semantic", lexicon=Lexicon.none(), step=1, metrics={}))
    actions = probe.record("action", String, EVENT_QOS)
    node = PolicyNode(context=probe.context, namespace=probe.namespace,
                      parameter_overrides=parameters(checkpoint=str(path), max_steps=3))
    probe.executor.add_node(node)
    node.on_graph(graph(), source_info())
    for value in range(4):
        node.on_observation(observation(value), source_info())
    probe.spin_until(lambda: actions and actions[-1].data == "<eos>", what="the episode's end")
    assert 1 <= len(actions) <= 4
    assert all(Action.from_token(a.data) in Action for a in actions)


def test_the_default_cap_is_the_policys_max_steps_in_the_node_and_in_params_yaml(probe):
    """config/params.yaml cannot import MAX_STEPS, so it repeats the value; this keeps the two equal."""
    params = yaml.safe_load((Path(__file__).resolve().parents[1] / "config" / "params.yaml").read_text())
    assert params["/**/policy_node"]["ros__parameters"]["max_steps"] == MAX_STEPS
    node, _ = start(probe, [Action.EOS])
    assert node.get_parameter("max_steps").value == MAX_STEPS


def test_model_eos_ends_the_episode(probe):
    actions = probe.record("action", String, EVENT_QOS)
    node, policy = start(probe, [Action.TURN_LEFT, Action.EOS, Action.WALK])
    node.on_graph(graph(), source_info())
    for _ in range(4):
        node.on_observation(observation(), source_info())
    probe.spin_until(lambda: len(actions) == 2, what="turn left and <eos>")
    assert [a.data for a in actions] == ["turn left", "<eos>"]
    assert len(policy.seen) == 2


def test_a_command_after_eos_starts_at_once_from_the_newest_state(probe):
    """The world does not reply to <eos>, so the next command acts on the state it left."""
    node, policy = start(probe, [Action.EOS])
    node.on_observation(observation(0), source_info())
    node.on_graph(graph(), source_info())  # -> <eos>
    node.on_graph(graph("push a big square"), source_info())
    assert policy.resets == ["walk to a red circle while spinning", "push a big square"]
    assert len(policy.seen) == 2


def test_a_new_graph_preempts_and_waits_for_the_reply_to_the_last_action(probe):
    status = probe.record("status", String, EVENT_QOS)
    node, policy = start(probe, [Action.WALK])
    node.on_graph(graph("walk to a red circle while spinning"), source_info())
    node.on_observation(observation(), source_info())
    node.on_graph(graph("push a big square"), source_info())
    assert policy.resets == ["walk to a red circle while spinning", "push a big square"]
    assert len(policy.seen) == 1  # the newest observation predates the in-flight walk
    node.on_observation(observation(), source_info())
    assert len(policy.seen) == 2
    probe.spin_until(lambda: any("preempted: 'walk to a red circle while spinning': a new command came after 1 "
                                 "actions" in s.data for s in status), what="the preemption notice")


@pytest.mark.parametrize("data", ["{not json", '{"schema_version": 1}', ""])
def test_bad_graphs_are_reported_and_the_node_stays_idle(probe, data):
    status = probe.record("status", String, EVENT_QOS)
    node, policy = start(probe, [Action.WALK])
    node.on_graph(text_to_cdr(data), source_info())
    node.on_observation(observation(), source_info())
    assert policy.seen == []
    probe.spin_until(lambda: any("bad command graph" in s.data for s in status), what="a rejection")


def test_an_observation_of_another_grid_size_is_reported_and_not_acted_on(probe):
    status = probe.record("status", String, EVENT_QOS)
    node, policy = start(probe, [Action.WALK])
    node.on_graph(graph(), source_info())
    node.on_observation(observation_to_cdr(np.zeros((12, 12, 16), dtype=np.uint8)), source_info())
    assert policy.seen == []
    probe.spin_until(lambda: any("12x12 grid; the model was trained on 6x6" in s.data for s in status),
                     what="a rejection")


def test_after_a_grid_size_mismatch_each_command_is_rejected_until_the_checkpoint_fits(probe):
    """A world of another size than the checkpoint's: the running episode is cut (`<eos>`,
    ABORTED: it had been accepted) and every later command is REJECTED, with the reason (no
    episode waits forever); a checkpoint that fits the world is followed from the next
    command on."""
    from actionlib_msgs.msg import GoalStatus

    from msg_adapters import cdr_to_episode_status

    reports = probe.record("episode_status", GoalStatus, EVENT_QOS, raw=True)
    actions = probe.record("action", String, EVENT_QOS)
    node, policy = start(probe, [Action.WALK])
    node.on_graph(graph(), source_info())
    node.on_observation(observation_to_cdr(np.zeros((12, 12, 16), dtype=np.uint8)), source_info())
    node.on_graph(graph("walk to a circle"), source_info())
    probe.spin_until(lambda: len(reports) == 3, what="three reports")
    told = [cdr_to_episode_status(r) for r in reports]
    assert [r.outcome for r in told] == ["active", "cut", "rejected"]
    probe.spin_until(lambda: [a.data for a in actions] == ["<eos>"], what="the forced <eos>")
    assert all("12x12 grid; the model was trained on 6x6" in r.text for r in told[1:])
    # the graph is fine; the world is not
    assert told[2].text.startswith("not following 'walk to a circle': the observation is on a 12x12 grid")
    assert policy.seen == [] and policy.resets == ["walk to a red circle while spinning"]
    fitting = ScriptedPolicy([Action.WALK])
    fitting.grid_size, fitting.observation_shape = 12, (12, 12, 16)
    node._next_policy = fitting  # what an accepted `checkpoint` change installs for the next command
    node.on_graph(graph("walk to a circle"), source_info())
    assert fitting.resets == ["walk to a circle"] and len(fitting.seen) == 1


def test_a_policy_stopped_mid_episode_reports_the_episode_preempted(probe):
    """Its clients and recorders learn the episode ended, instead of waiting for it forever."""
    from actionlib_msgs.msg import GoalStatus

    from gscan_ros import episode_status as es

    reports = probe.record("episode_status", GoalStatus, EVENT_QOS, raw=True)
    node, policy = start(probe, [Action.WALK])
    node.on_graph(graph(), source_info())
    node.on_observation(observation(0), source_info())  # -> walk; waits for the world's reply
    probe.executor.remove_node(node)
    node.destroy_node()
    probe.spin_until(lambda: len(reports) == 2, what="the end report")
    active, end = (cdr_to_episode_status(r) for r in reports)
    assert (end.episode_id, end.start_ns, end.outcome) == (active.episode_id, active.start_ns, es.PREEMPTED)
    assert end.text.endswith("the policy stopped after 1 actions")


def test_a_graph_of_another_parser_is_rejected(probe):
    status = probe.record("status", String, EVENT_QOS)
    node, policy = start(probe, [Action.WALK])
    node.on_graph(graph_to_cdr(get_parser("dependency").parse("walk to a red circle")), source_info())
    assert policy.resets == []
    probe.spin_until(lambda: any("'dependency' parser" in s.data for s in status), what="a rejection")


def test_attention_maps_are_published_per_word(probe):
    """Each map is stamped with the header of the observation it was computed from."""
    red = probe.record("attention/red", Image, VIEWER_LOG_QOS, raw=True)  # best effort, as offered
    spinning = probe.record("attention/while_spinning", Image, VIEWER_LOG_QOS, raw=True)
    node, _ = start(probe, [Action.WALK], attention_upsample=4)
    node.on_graph(graph(), source_info())
    state_ns = 1_700_000_000_123_456_789
    node.on_observation(observation(header=grid_header(state_ns)), source_info())
    deadline = time.monotonic() + 30
    while not (red and spinning):  # the publishers appear with the first step: allow discovery
        assert time.monotonic() < deadline, "no attention maps"
        node.on_observation(observation(header=grid_header(state_ns)), source_info())
        probe.executor.spin_once(timeout_sec=0.05)
    msg = cdr_to_msg(red[0], "sensor_msgs/msg/Image")
    assert (msg.height, msg.width, msg.encoding) == (24, 24, "mono8")
    assert (time_ns(msg.header.stamp), msg.header.frame_id) == (state_ns, "gscan_grid")
    np.testing.assert_allclose(cdr_to_attention(red[0]), np.eye(6))
    np.testing.assert_allclose(cdr_to_attention(spinning[0]), np.eye(6)[::-1])
    viewers = [pub for pub in node.publishers if pub.topic_name.startswith(f"{probe.namespace}/attention/")]
    assert viewers and all(pub.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for pub in viewers)


def world_reset(t_ns=None):
    return reset_to_cdr(time.time_ns() if t_ns is None else t_ns)


def test_a_world_reset_aborts_the_running_episode(probe):
    actions = probe.record("action", String, EVENT_QOS)
    status = probe.record("status", String, EVENT_QOS)
    node, policy = start(probe, [Action.WALK])
    node.on_graph(graph(), source_info())
    node.on_observation(observation(0), source_info())  # -> walk
    node.on_world_reset(world_reset(), source_info())
    node.on_observation(observation(1), source_info())  # the new world's first state
    assert len(policy.seen) == 1  # no action for the old command in the new world
    probe.spin_until(lambda: any("preempted: 'walk to a red circle while spinning': the world was reset after 1 "
                                 "actions" in s.data for s in status), what="the abort notice")
    node.on_graph(graph("push a big square"), source_info())  # a new command starts in the new world
    assert len(policy.seen) == 2 and policy.seen[1][1, 0, 11] == 1
    probe.spin_until(lambda: len(actions) == 2, what="two walks")
    assert "<eos>" not in [a.data for a in actions]  # aborted, not ended


def test_state_and_commands_from_before_a_reset_are_ignored(probe):
    node, policy = start(probe, [Action.WALK])
    before_reset = time.time_ns()
    node.on_world_reset(world_reset(), source_info())
    node.on_observation(observation(0), source_info(t_ns=before_reset))  # the old world's, delivered late
    node.on_graph(graph("push a big square"), source_info(t_ns=before_reset))  # a command for the old world
    assert policy.resets == []
    node.on_graph(graph(), source_info())
    assert policy.seen == []  # waits for the new world's state
    node.on_observation(observation(1), source_info())
    assert len(policy.seen) == 1


def test_a_graph_with_a_huge_arity_is_reported_and_the_node_keeps_following_commands(probe):
    """The 308-byte message that took the policy from 0.33 to 2.3 GB."""
    import json

    status = probe.record("status", String, EVENT_QOS)
    node, policy = start(probe, [Action.WALK])
    bad = json.loads(cdr_to_text(graph()))
    bad["nodes"][-1]["arity"] = 50_000_000
    node.on_graph(text_to_cdr(json.dumps(bad)), source_info())
    probe.spin_until(lambda: any("bad command graph" in s.data and "arity is 50000000" in s.data
                                 for s in status), what="the rejection")
    node.on_observation(observation(), source_info())
    node.on_graph(graph(), source_info())
    assert len(policy.seen) == 1


def test_size_ordering_is_published_for_a_size_word(probe):
    """(-att_small + att_big) / 2 from the word's map and its antonym head's map, shifted to
    start at 0: darkest at the small object, lightest at the big one."""
    class SizePolicy(ScriptedPolicy):
        def step(self, observation):
            small, big = np.zeros((6, 6), np.float32), np.zeros((6, 6), np.float32)
            small[0, 0], big[5, 5] = 1.0, 1.0
            return StepOutput(super().step(observation).action, {"small": small}, {"small": big})

    ordering = probe.record("attention/size_ordering", Image, VIEWER_LOG_QOS, raw=True)
    node = PolicyNode(SizePolicy([Action.WALK]), context=probe.context, namespace=probe.namespace,
                      parameter_overrides=parameters())
    probe.executor.add_node(node)
    node.on_graph(graph("walk to a small circle"), source_info())
    deadline = time.monotonic() + 30
    while not ordering:  # the publisher appears with the first step: allow discovery
        assert time.monotonic() < deadline, "no size-ordering map"
        node.on_observation(observation(), source_info())
        probe.executor.spin_once(timeout_sec=0.05)
    expected = np.full((6, 6), 0.5)
    expected[0, 0], expected[5, 5] = 0.0, 1.0
    np.testing.assert_allclose(cdr_to_attention(ordering[0]), expected, atol=1 / 255)


def told(reports) -> list[tuple[str, str]]:
    """(outcome, text) of each `episode_status` report received."""
    return [(r.outcome, r.text) for r in map(cdr_to_episode_status, reports)]


def test_every_graph_that_comes_while_the_node_is_busy_gets_its_reports(probe):
    """Two graphs queued before the node takes either: both are followed in order (the first
    preempted by the second), none is overwritten without a report."""
    from actionlib_msgs.msg import GoalStatus

    reports = probe.record("episode_status", GoalStatus, EVENT_QOS, raw=True)
    node, policy = start(probe, [Action.WALK])
    graphs = probe.node.create_publisher(String, "command_graph", qos_profile(interface.COMMAND_GRAPH))
    probe.spin_until(lambda: graphs.get_subscription_count() >= 1, what="the policy's graph subscription")
    graphs.publish(graph("walk to a red circle"))
    graphs.publish(graph("push a big square"))
    probe.spin_until(lambda: len(reports) == 3, what="three reports")
    assert told(reports) == [("active", "walk to a red circle"),
                             ("preempted", "'walk to a red circle': a new command came after 0 actions"),
                             ("active", "push a big square")]
    assert policy.resets == ["walk to a red circle", "push a big square"]


def test_a_graph_from_before_the_start_is_ignored_and_one_from_before_the_last_reset_rejected(probe):
    """The latched copy a restarted policy receives starts no episode and takes no id (a
    recorder would count it as a new rejected command); a command overtaken by a reset is
    answered REJECTED."""
    from actionlib_msgs.msg import GoalStatus

    reports = probe.record("episode_status", GoalStatus, EVENT_QOS, raw=True)
    status = probe.record("status", String, EVENT_QOS)
    node, policy = start(probe, [Action.WALK])
    node.on_graph(graph(), source_info(t_ns=1))  # the latched copy a restarted policy receives
    before_reset = time.time_ns()
    node.on_world_reset(world_reset(), source_info())
    node.on_graph(graph("push a big square"), source_info(t_ns=before_reset))
    probe.spin_until(lambda: len(reports) == 1, what="one report")
    assert told(reports) == [
        ("rejected", "not following 'push a big square': its graph was published before the world was reset")]
    assert cdr_to_episode_status(reports[0]).episode_id.endswith("/1")  # the ignored graph took no id
    probe.spin_until(lambda: any("ignored the graph of 'walk to a red circle while spinning': published before "
                                 "this node started" in s.data for s in status), what="the status line")
    assert policy.resets == []


def test_a_world_reset_stamped_in_the_future_does_not_stop_the_node(probe):
    """The reset's time is when it was published (DDS source timestamp), not what its header claims."""
    node, policy = start(probe, [Action.WALK])
    a_year_ns = 365 * 24 * 3600 * 10**9
    node.on_world_reset(world_reset(time.time_ns() + a_year_ns), source_info())
    node.on_observation(observation(0), source_info())
    node.on_graph(graph(), source_info())
    assert len(policy.seen) == 1


def test_an_observation_from_before_the_reset_is_dropped_with_a_status_line(probe):
    status = probe.record("status", String, EVENT_QOS)
    node, policy = start(probe, [Action.WALK])
    before_reset = time.time_ns()
    node.on_world_reset(world_reset(), source_info())
    node.on_observation(observation(0), source_info(t_ns=before_reset))
    probe.spin_until(lambda: any("ignored an observation published before the world was reset" in s.data
                                 for s in status), what="the notice")


def test_a_map_that_cannot_be_published_is_reported_and_the_episode_goes_on_to_its_end(probe):
    from actionlib_msgs.msg import GoalStatus

    class NanMaps(ScriptedPolicy):
        def step(self, observation):
            return StepOutput(super().step(observation).action, {"red": np.full((6, 6), np.nan, np.float32)})

    reports = probe.record("episode_status", GoalStatus, EVENT_QOS, raw=True)
    status = probe.record("status", String, EVENT_QOS)
    node = PolicyNode(NanMaps([Action.WALK, Action.EOS]), context=probe.context, namespace=probe.namespace,
                      parameter_overrides=parameters())
    probe.executor.add_node(node)
    node.on_graph(graph(), source_info())
    node.on_observation(observation(0), source_info())  # walk
    node.on_observation(observation(1), source_info())  # <eos>
    probe.spin_until(lambda: len(reports) == 2, what="the episode's end")
    assert told(reports)[1] == ("complete", "'walk to a red circle while spinning': done after 1 actions")
    probe.spin_until(lambda: sum("attention maps of step" in s.data and "not published: attention map must hold "
                                 "finite non-negative weights" in s.data for s in status) == 2, what="two notices")


def test_a_failing_step_ends_the_episode_aborted_and_the_next_command_is_followed(probe):
    from actionlib_msgs.msg import GoalStatus

    def fail_second(t):
        if t == 1:
            raise RuntimeError("CUDA out of memory")

    actions = probe.record("action", String, EVENT_QOS)
    reports = probe.record("episode_status", GoalStatus, EVENT_QOS, raw=True)
    status = probe.record("status", String, EVENT_QOS)
    policy = ScriptedPolicy([Action.WALK], on_step=fail_second)
    node = PolicyNode(policy, context=probe.context, namespace=probe.namespace, parameter_overrides=parameters())
    probe.executor.add_node(node)
    node.on_graph(graph(), source_info())
    node.on_observation(observation(0), source_info())  # walk
    node.on_observation(observation(1), source_info())  # the step fails
    probe.spin_until(lambda: len(actions) == 2 and len(reports) == 2, what="the forced <eos> and the end")
    assert [a.data for a in actions] == ["walk", "<eos>"]
    assert told(reports)[1] == ("cut", "'walk to a red circle while spinning': step 1 failed: RuntimeError: CUDA out "
                                       "of memory")
    assert cdr_to_msg(reports[1], "actionlib_msgs/msg/GoalStatus").status == GoalStatus.ABORTED
    probe.spin_until(lambda: any("internal error in the policy's step: RuntimeError: CUDA out of memory" in s.data
                                 for s in status), what="the error")
    node.on_graph(graph("push a big square"), source_info())  # a new episode starts at once (t is 0 again)
    assert policy.resets[-1] == "push a big square" and len(policy.seen) == 2


def test_an_episode_whose_reply_never_comes_ends_aborted_after_step_timeout(probe):
    """0 waits forever; a new value applies at once; the episode ends with a forced <eos>."""
    from actionlib_msgs.msg import GoalStatus

    actions = probe.record("action", String, EVENT_QOS)
    reports = probe.record("episode_status", GoalStatus, EVENT_QOS, raw=True)
    status = probe.record("status", String, EVENT_QOS)
    node, policy = start(probe, [Action.WALK], step_timeout=0.0)
    [described] = node.describe_parameters(["step_timeout"])
    assert described.floating_point_range and described.floating_point_range[0].from_value == 0.0
    node.on_graph(graph(), source_info())
    node.on_observation(observation(0), source_info())  # walk
    time.sleep(0.05)
    node.check_step()
    node.on_observation(observation(1), source_info())  # still running: the reply is followed
    assert len(policy.seen) == 2
    [result] = node.set_parameters(parameters(step_timeout=0.05))
    assert result.successful
    time.sleep(0.1)  # the reply to the second walk is lost
    node.check_step()
    probe.spin_until(lambda: len(actions) == 3 and len(reports) == 2, what="the forced <eos> and the end")
    assert [a.data for a in actions] == ["walk", "walk", "<eos>"]
    assert told(reports)[1] == ("cut", "'walk to a red circle while spinning': no observation came within "
                                       "step_timeout=0.05 s after action 1")
    probe.spin_until(lambda: any("step_timeout=0.05 s" in s.data for s in status), what="the status line")
    # A command before any new state is refused at once (the world may have taken that
    # walk), not left waiting step_timeout for a reply that will not come.
    node.on_graph(graph(), source_info())
    probe.spin_until(lambda: len(reports) == 3, what="the refusal")
    assert told(reports)[2][0] == "rejected" and "the world never replied to action 1 of episode" in told(reports)[2][1]
    node.on_observation(observation(2), source_info())  # the late reply starts nothing
    assert len(policy.seen) == 2
    node.on_graph(graph(), source_info())  # with a state to start from, the next command is followed
    assert len(policy.seen) == 3


def test_step_timeout_takes_an_integer_as_ros2_param_set_sends_it(probe):
    """`-p step_timeout:=60` and `ros2 param set /policy_node step_timeout 5` send integers."""
    node, _ = start(probe, [Action.WALK], step_timeout=60)
    assert node.step_timeout == 60.0
    [result] = node.set_parameters(parameters(step_timeout=5))
    assert result.successful and node.step_timeout == 5.0
    for bad, reason in ((-1, "must lie in [0, 86400]"), (10**9, "must lie in [0, 86400]"), (1e9, "out of range"),
                        ("soon", "must be a number")):
        [result] = node.set_parameters(parameters(step_timeout=bad))
        assert not result.successful and reason in result.reason, bad
    assert node.step_timeout == 5.0
    with pytest.raises(GscanError, match="step_timeout must lie in"):
        start(probe, [Action.WALK], step_timeout=-3)


def test_the_watchdog_runs_with_use_sim_time_and_no_clock(probe):
    """A launch file may set use_sim_time for every node; with no /clock the node clock
    stands still, and a watchdog on it would leave the episode ACTIVE for ever."""
    from actionlib_msgs.msg import GoalStatus

    reports = probe.record("episode_status", GoalStatus, EVENT_QOS, raw=True)
    node, policy = start(probe, [Action.WALK], step_timeout=0.05, use_sim_time=True)
    node.on_graph(graph(), source_info())
    node.on_observation(observation(0), source_info())  # walk; its reply never comes
    probe.spin_until(lambda: len(reports) == 2, what="the watchdog's end of the episode")  # the timer, not a call
    assert told(reports)[1][0] == "cut" and "step_timeout=0.05 s after action 0" in told(reports)[1][1]


def test_torch_threads_0_gives_the_model_torchs_default_again(probe, monkeypatch):
    threads = torch.get_num_threads()
    monkeypatch.setattr(runtime, "_default_threads", None)
    torch.set_num_threads(3)  # torch's default in this process, as configure_torch first finds it
    try:
        node, _ = start(probe, [Action.EOS], torch_threads=2)
        assert torch.get_num_threads() == 2
        node.set_parameters(parameters(torch_threads=0))
        assert torch.get_num_threads() == 3
    finally:
        torch.set_num_threads(threads)
