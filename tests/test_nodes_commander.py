"""GscanCommander against an in-process stack (scripted policy): one EpisodeResult per command, each outcome."""
import threading

import pytest
from std_msgs.msg import String
from std_srvs.srv import Trigger

from gscan_ros import episode_status as es
from gscan_ros.language import get_parser
from gscan_ros.nodes.commander import GscanCommander, Outcome, _episode_reports
from gscan_ros.nodes.common import EVENT_QOS, command_refusal
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
    assert result.episode_id == "/policy_node/1" and result.reason.endswith("done after 2 actions")
    assert 0 < result.elapsed < TIMEOUT


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
    assert result.reason.startswith("rejected command 'fly to the moon'") and result.episode_id == "/parser_node/1"


def test_a_world_reset_preempts_the_episode(probe, commander, checkpoint):
    nodes = {}

    def reset_at_step_2(t):
        if t == 2:
            nodes["world"].on_reset_world(Trigger.Request(), Trigger.Response())

    nodes["world"] = start(probe, commander, checkpoint, [WALK], on_step=reset_at_step_2).world
    result = commander.run_episode("walk to a red circle", timeout=TIMEOUT)
    assert result.outcome is Outcome.PREEMPTED and EOS not in result.actions
    # The scripted policy is reset inside its third step, whose action still goes out.
    assert result.reason.endswith("the world was reset after 3 actions") and result.steps == 3


def test_another_command_preempts_the_episode(probe, commander, checkpoint):
    other = probe.node.create_publisher(String, "command", EVENT_QOS)

    def command_at_step_2(t):
        if t == 2:
            other.publish(String(data="push a big square"))

    start(probe, commander, checkpoint, [WALK], on_step=command_at_step_2)
    result = commander.run_episode("walk to a red circle", timeout=TIMEOUT)
    # The other command is published inside the third step, whose action still goes out.
    assert result.outcome is Outcome.PREEMPTED and result.steps == 3
    assert result.reason == "'walk to a red circle': a new command came after 3 actions"


def test_actions_that_come_after_the_end_report_still_count(probe, checkpoint, monkeypatch):
    """Actions and reports travel on different topics: an ending without <eos> still waits for
    the actions published before it (here every action is held back 0.1 s on arrival)."""
    on_action = GscanCommander._on_action
    monkeypatch.setattr(GscanCommander, "_on_action",
                        lambda self, data, info: threading.Timer(0.1, on_action, (self, data, info)).start())
    other = probe.node.create_publisher(String, "command", EVENT_QOS)

    def command_at_step_2(t):
        if t == 2:
            other.publish(String(data="push a big square"))

    with GscanCommander(context=probe.context) as commander:
        start(probe, commander, checkpoint, [WALK], on_step=command_at_step_2)
        result = commander.run_episode("walk to a red circle", timeout=TIMEOUT)
    assert result.outcome is Outcome.PREEMPTED and result.actions == [WALK] * 3


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


def test_the_commander_needs_no_node_names(probe, commander, checkpoint):
    """Renamed nodes (`--ros-args -r __node:=brain`): readiness and outcomes come from the
    topics and the typed episode reports, not from names."""
    names = {"policy_node": "brain", "parser": "ears", "world": "grid"}
    start(probe, commander, checkpoint, [WALK, EOS], names=names)
    result = commander.run_episode("walk to a red circle", timeout=TIMEOUT)
    assert (result.outcome, result.actions, result.episode_id) == (Outcome.SUCCEEDED, [WALK, EOS], "/brain/1")
    refused = commander.run_episode("fly to the moon", timeout=TIMEOUT)
    assert (refused.outcome, refused.episode_id) == (Outcome.REJECTED, "/ears/1")


def test_another_clients_refused_command_is_not_taken_for_ones_own():
    """Between the graph of a client's command and its episode's ACTIVE report, the parser
    may refuse another client's command: the client still gets its own episode."""
    graph = get_parser("semantic").parse("walk to a circle")
    other = es.EpisodeStatus("/parser_node/1", 11, es.REJECTED, f"{command_refusal('jump')}: not a gSCAN command")
    active = es.EpisodeStatus("/policy_node/1", 12, es.ACTIVE, "walk to a circle")
    done = es.EpisodeStatus("/policy_node/1", 12, es.COMPLETE, "'walk to a circle': done after 2 actions")
    reports = [(11, other), (12, active), (13, done)]
    assert _episode_reports(reports, 5, "walk to a circle", (10, graph)) == ((12, active), (13, done))
    # The policy's refusal of the graph (no ACTIVE before it) is the command's outcome.
    refused = es.EpisodeStatus("/policy_node/1", 12, es.REJECTED, "bad command graph: no module for 'circle'")
    assert _episode_reports([(11, other), (12, refused)], 5, "walk to a circle", (10, graph)) == (None, (12, refused))
    # The parser's refusal of the command itself.
    own = es.EpisodeStatus("/parser_node/2", 11, es.REJECTED, f"{command_refusal('fly')}: not a gSCAN command")
    assert _episode_reports([(11, own)], 5, "fly", None) == (None, (11, own))
