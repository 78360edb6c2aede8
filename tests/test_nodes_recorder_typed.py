"""The recorded episode header keeps the command as typed next to the canonical one."""
import json
import random
import time

import pytest
from std_msgs.msg import String

from gscan_ros.data.bag import BagEpisodeReader
from gscan_ros.data.sources import sample_episode
from gscan_ros.language import get_parser
from gscan_ros.language.paraphrase import paraphrase
from gscan_ros.nodes.episode_recorder_node import EpisodeRecorderNode
from gscan_ros.world import World
from gscan_ros.world.types import Action
from msg_adapters import action_to_msg, graph_to_msg, observation_to_msg

from ros_helpers import Probe, fresh_domain_id, parameters

EPISODE = sample_episode(0)


@pytest.fixture
def recorder(tmp_path):
    probe = Probe(fresh_domain_id())
    node = EpisodeRecorderNode(context=probe.context, parameter_overrides=parameters(bag_dir=str(tmp_path / "bag")))
    yield node
    node.destroy_node()
    probe.close()


def record_one_step_episode(recorder, command: str) -> dict:
    """World state, the command's graph, one WALK and <eos> into the callbacks; the written header."""
    stamps = iter(range(time.time_ns(), time.time_ns() + 10**9, 1000))
    world = World(EPISODE.situation)

    def state():
        recorder.on_situation(String(data=json.dumps(world.snapshot().to_json())), {"source_timestamp": next(stamps)})
        recorder.on_observation(observation_to_msg(world.encode()), {"source_timestamp": next(stamps)})

    state()
    recorder.on_graph(graph_to_msg(get_parser("semantic").parse(command)), {"source_timestamp": next(stamps)})
    for seq, action in enumerate((Action.WALK, Action.EOS), start=1):
        info = {"source_timestamp": next(stamps), "publication_sequence_number": seq}
        recorder.on_action(action_to_msg(action), info)
        if action is not Action.EOS:
            world.step(action)
            state()
    [record] = list(BagEpisodeReader(recorder.bag_dir).records())
    return record.header


def test_header_keeps_the_typed_and_the_canonical_command(recorder):
    typed = paraphrase(EPISODE.command, random.Random(1))
    assert typed != EPISODE.command
    header = record_one_step_episode(recorder, typed)
    assert header["command"] == EPISODE.command and header["meta"]["typed_command"] == typed


def test_a_canonical_command_records_no_typed_copy(recorder):
    assert "typed_command" not in record_one_step_episode(recorder, EPISODE.command)["meta"]
