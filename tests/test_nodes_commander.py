"""GscanCommander against an in-process stack (scripted policy): one EpisodeResult per command, each outcome."""
import pytest
from std_msgs.msg import String
from std_srvs.srv import Trigger

from gscan_ros.language import get_parser
from gscan_ros.nodes.commander import GscanCommander, Outcome, _EpisodeWatch
from gscan_ros.nodes.common import EVENT_QOS
from gscan_ros.world.types import Action

from ros_helpers import in_process_stack

WALK, TURN, EOS = Action.WALK, Action.TURN_LEFT, Action.EOS
TIMEOUT = 30.0


@pytest.fixture
def commander(probe):
    c = GscanCommander(context=probe.context, attention_words=["red"])
    yield c
    c.shutdown()


def start(probe, commander, checkpoint, script, **kwargs):
    stack = in_process_stack(probe, checkpoint, script, **kwargs)
    commander.wait_until_ready(TIMEOUT)
    return stack


def test_an_episode_that_the_policy_ends_succeeds(probe, commander, checkpoint):
    start(probe, commander, checkpoint, [WALK, TURN, EOS])
    result = commander.run_episode("walk to a red circle", timeout=TIMEOUT)
    assert result.outcome is Outcome.SUCCEEDED and result.succeeded and result.finished
    assert result.actions == [WALK, TURN, EOS] and result.moves == [WALK, TURN] and result.steps == 2
    assert result.graph.command == "walk to a red circle" and result.command == "walk to a red circle"
    assert len(result.action_times_ns) == 3 and all(t >= result.sent_ns for t in result.action_times_ns)
    assert any(line.startswith("policy_node: done with") for line in result.status)
    assert 0 < result.elapsed < TIMEOUT


def test_an_episode_waits_for_its_graph_when_the_eos_comes_first():
    """Topics are not ordered with each other: on a busy machine the <eos> action can
    arrive before the command graph, and the episode is closed only once both are in."""
    watch = _EpisodeWatch("walk to a large circle")
    lines = ["policy_node: following 'walk to a big circle'", "policy_node: done with 'walk to a big circle'"]
    assert watch.update(None, lines, [(1, 2, EOS)]) == (Outcome.SUCCEEDED, "") and watch.eos_seen
    assert not watch.closed(lines)
    watch.see(get_parser("semantic").parse("walk to a large circle"))
    assert watch.closed(lines) and not watch.closed(lines[:1])


def test_a_paraphrase_is_followed_as_its_gscan_command(probe, commander, checkpoint):
    start(probe, commander, checkpoint, [EOS])
    result = commander.run_episode("walk to a large circle", timeout=TIMEOUT)
    assert result.outcome is Outcome.SUCCEEDED
    assert (result.graph.command, result.graph.typed) == ("walk to a big circle", "walk to a large circle")


def test_an_episode_cut_by_max_steps_says_so(probe, commander, checkpoint):
    start(probe, commander, checkpoint, [WALK], max_steps=3)
    result = commander.run_episode("walk to a red circle", timeout=TIMEOUT)
    assert result.outcome is Outcome.MAX_STEPS and result.finished and not result.succeeded
    assert result.actions == [WALK, WALK, WALK, EOS]


def test_a_command_the_parser_refuses_is_rejected_with_its_reason(probe, commander, checkpoint):
    start(probe, commander, checkpoint, [WALK])
    result = commander.run_episode("fly to the moon", timeout=TIMEOUT)
    assert result.outcome is Outcome.REJECTED and result.actions == [] and result.graph is None
    assert result.reason.startswith("parser_node: rejected command 'fly to the moon'") and "fly" in result.reason


def test_a_world_reset_aborts_the_episode(probe, commander, checkpoint):
    nodes = {}

    def reset_at_step_2(t):
        if t == 2:
            nodes["world"].on_reset_world(Trigger.Request(), Trigger.Response())

    nodes["world"] = start(probe, commander, checkpoint, [WALK], on_step=reset_at_step_2).world
    result = commander.run_episode("walk to a red circle", timeout=TIMEOUT)
    assert result.outcome is Outcome.ABORTED and EOS not in result.actions
    assert "the world was reset" in result.reason


def test_another_command_preempts_the_episode(probe, commander, checkpoint):
    other = probe.node.create_publisher(String, "command", EVENT_QOS)

    def command_at_step_2(t):
        if t == 2:
            other.publish(String(data="push a big square"))

    start(probe, commander, checkpoint, [WALK], on_step=command_at_step_2)
    result = commander.run_episode("walk to a red circle", timeout=TIMEOUT)
    assert result.outcome is Outcome.PREEMPTED
    assert result.reason.startswith("policy_node: preempted 'walk to a red circle'")


def test_an_episode_without_end_times_out_and_reset_world_answers(probe, commander, checkpoint):
    start(probe, commander, checkpoint, [WALK], max_steps=100_000)
    result = commander.run_episode("walk to a red circle", timeout=1.0)
    assert result.outcome is Outcome.TIMEOUT and result.steps >= 1 and EOS not in result.actions
    assert result.attention["red"]  # the watched word's maps (best effort) came with the steps
    assert "seed 4" in commander.reset_world(TIMEOUT)  # the world's next situation


def test_connect_owns_its_context(probe, checkpoint):
    start_stack = in_process_stack(probe, checkpoint, [TURN, EOS])
    with GscanCommander.connect(probe.context.get_domain_id(), node_name="second_commander") as commander:
        commander.wait_until_ready(TIMEOUT)
        assert commander.run_episode("walk to a red circle", timeout=TIMEOUT).actions == [TURN, EOS]
        context = commander.context
    assert not context.ok()
    assert start_stack.policy.resets == ["walk to a red circle"]
