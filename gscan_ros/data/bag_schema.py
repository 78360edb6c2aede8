"""Topics and QoS of gscan_ros bags (rosbag2 + MCAP, docs/bags.md).

Topic names, types and offered QoS come from the stack's interface table
(`gscan_ros.interface`), so a bag records what the live publishers offer. The schema
text and type hash of each type come from `msg_adapters` (rosbags' type store), so a
bag is written without ROS installed.
"""
from __future__ import annotations

from dataclasses import dataclass

import yaml

from gscan_ros import interface
from gscan_ros.interface import Endpoint, Qos

# QoS as recorded in rosbag2 metadata (version 9: a list of profiles, durations {sec, nsec}).
_INFINITE = {"sec": 2147483647, "nsec": 4294967295}


def rosbag2_qos(qos: Qos) -> dict:
    """One offered QoS profile of the interface table, keys in rosbag2's order."""
    return {
        "history": "keep_last",
        "depth": qos.depth,
        "reliability": qos.reliability,
        "durability": qos.durability,
        "deadline": dict(_INFINITE),
        "lifespan": dict(_INFINITE),
        "liveliness": "automatic",
        "liveliness_lease_duration": dict(_INFINITE),
        "avoid_ros_namespace_conventions": False,
    }


# A topic outside the interface table (someone else's, mixed into a bag): rosbag2's default.
DEFAULT_QOS = rosbag2_qos(Qos(10))


class YamlDumper(yaml.SafeDumper):
    """Plain YAML for rosbag2 files: no &anchors / *aliases for repeated sub-dicts."""

    def ignore_aliases(self, data) -> bool:
        return True


@dataclass(frozen=True)
class TopicSpec:
    """A recorded topic of the interface table, named as the bag stores it."""

    name: str  # absolute topic name as stored in the bag
    msg_type: str  # "pkg/msg/Type"
    offered: Qos  # what the live publisher offers (gscan_ros.interface)
    earlier_types: tuple[str, ...] = ()  # what bags written by earlier versions hold instead (still read)

    def carries(self, msg_type: str) -> bool:
        return msg_type == self.msg_type or msg_type in self.earlier_types

    @property
    def latched(self) -> bool:
        return self.offered.latched

    @property
    def qos(self) -> dict:
        return rosbag2_qos(self.offered)


_EARLIER_TYPES = {interface.OBSERVATION.name: (interface.EARLIER_OBSERVATION_TYPE,)}


def _spec(endpoint: Endpoint) -> TopicSpec:
    return TopicSpec(endpoint.bag_topic, endpoint.type, endpoint.qos, _EARLIER_TYPES.get(endpoint.name, ()))


COMMAND = _spec(interface.COMMAND)
COMMAND_GRAPH = _spec(interface.COMMAND_GRAPH)
OBSERVATION = _spec(interface.OBSERVATION)
ACTION = _spec(interface.ACTION)
WORLD_IMAGE = _spec(interface.WORLD_IMAGE)
SITUATION = _spec(interface.SITUATION)
WORLD_RESET = _spec(interface.WORLD_RESET)
EPISODE_STATUS = _spec(interface.EPISODE_STATUS)
EPISODE = _spec(interface.EPISODE)
TOPICS: dict[str, TopicSpec] = {t.name: t for t in map(_spec, interface.RECORDED)}


def offered_qos(topic: str) -> dict:
    """The rosbag2 QoS profile a bag records for `topic`: the interface table's, else rosbag2's default."""
    endpoint = interface.endpoint_of(topic)
    return rosbag2_qos(endpoint.qos) if endpoint is not None and endpoint.qos is not None else DEFAULT_QOS
