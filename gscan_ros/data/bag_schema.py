"""Topics, QoS and ros2msg schemas of gscan_ros bags (rosbag2 + MCAP, docs/bags.md).

Topic names, types and offered QoS come from the stack's interface table
(`gscan_ros.interface`), so a bag records what the live publishers offer.

The schema text is what rosbag2 itself records: the installed `.msg` file of the type
followed by every nested type's `.msg`, each introduced by a `MSG: pkg/Type` line under
a row of 80 '='. The RIHS01 type hash comes from the `.json` type description the ROS
build installs next to each `.msg`.
"""
from __future__ import annotations

import importlib
import json
import re
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import yaml

from gscan_ros import interface
from gscan_ros.interface import Endpoint, Qos

SEPARATOR = "=" * 80
PRIMITIVES = frozenset(
    "bool byte char float32 float64 int8 uint8 int16 uint16 int32 uint32 int64 uint64 string wstring".split()
)

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


def msg_type_name(msg_class: type) -> str:
    """"pkg/msg/Type" of a generated rosidl message class (e.g. std_msgs.msg.String)."""
    return f"{msg_class.__module__.split('.')[0]}/msg/{msg_class.__name__}"


def msg_class(type_name: str) -> type:
    """The generated Python class of "pkg/msg/Type"."""
    package, _, name = type_name.split("/")
    return getattr(importlib.import_module(f"{package}.msg"), name)


def _share_dir(package: str) -> Path:
    """share/<package> of an installed interface package (ament index, else next to its module)."""
    try:
        from ament_index_python.packages import get_package_share_directory

        return Path(get_package_share_directory(package))
    except (ImportError, LookupError, OSError, ValueError):
        module = Path(importlib.import_module(package).__file__).resolve()
        # <prefix>/lib/pythonX.Y/site-packages/<package>/__init__.py -> <prefix>/share/<package>
        return module.parents[4] / "share" / package


def _msg_file(type_name: str, suffix: str) -> Path:
    package, _, name = type_name.split("/")
    path = _share_dir(package) / "msg" / f"{name}{suffix}"
    if not path.is_file():
        raise FileNotFoundError(f"message definition {path} of {type_name} is not installed")
    return path


def _field_types(msg_text: str, package: str) -> list[str]:
    """Nested (non-primitive) field types of a .msg text, as "pkg/msg/Type"."""
    nested = []
    for line in msg_text.splitlines():
        tokens = line.split("#", 1)[0].split()
        if len(tokens) < 2 or "=" in tokens[1]:  # blank, comment or constant
            continue
        base = re.sub(r"\[.*\]$", "", tokens[0]).split("<=")[0]
        if base in PRIMITIVES:
            continue
        pkg, _, name = base.rpartition("/")
        nested.append(f"{pkg or package}/msg/{name}")
    return nested


@cache
def message_definition(type_name: str) -> str:
    """Full ros2msg schema text of "pkg/msg/Type" with all dependencies, as rosbag2 writes it."""
    parts, seen = [], set()

    def visit(name: str, top: bool) -> None:
        if name in seen:
            return
        seen.add(name)
        text = _msg_file(name, ".msg").read_text(encoding="utf-8").rstrip("\n")
        package, _, short = name.split("/")
        parts.append(text if top else f"{SEPARATOR}\nMSG: {package}/{short}\n{text}")
        for child in _field_types(text, package):
            visit(child, top=False)

    visit(type_name, top=True)
    return "\n".join(parts) + "\n"


@cache
def type_hash(type_name: str) -> str:
    """RIHS01 hash of the type ('' when the installed type description lacks one)."""
    try:
        description = json.loads(_msg_file(type_name, ".json").read_text(encoding="utf-8"))
    except FileNotFoundError:
        return ""
    for entry in description.get("type_hashes", []):
        if entry.get("type_name") == type_name:
            return entry.get("hash_string", "")
    return ""
