"""The ROS interface of the gscan_ros stack, as plain data: every topic and service, its type and QoS.

One table serves both layers: the nodes turn each entry's `Qos` into an rclpy
QoSProfile (`gscan_ros.nodes.common.qos_profile`), and the bag code records the same
offered QoS in metadata.yaml and the MCAP channels (`gscan_ros.data.bag_schema`), so a
replayed bag offers what the live stack offers. Nothing here imports rclpy: the data
layer reads this table too. Names are relative, so a whole stack can live in a
namespace; a bag stores them absolute (`Endpoint.bag_topic`). The one absolute name is
`/diagnostics`, where ROS tools expect every node's health.
"""
from __future__ import annotations

import re
from dataclasses import dataclass

RELIABLE, BEST_EFFORT = "reliable", "best_effort"
VOLATILE, TRANSIENT_LOCAL = "volatile", "transient_local"
TOPIC, SERVICE = "topic", "service"


@dataclass(frozen=True)
class Qos:
    """A KEEP_LAST QoS profile in rosbag2's words (`reliability`, `durability`)."""

    depth: int
    reliability: str = RELIABLE
    durability: str = VOLATILE

    @property
    def latched(self) -> bool:
        """TRANSIENT_LOCAL: a late subscriber still gets the stored samples."""
        return self.durability == TRANSIENT_LOCAL


# What writers offer.
# World-state-like topics: the current state only. A late subscriber (a viewer, `ros2 topic
# echo --once`) gets the newest sample and nothing stale; a reliable depth-1 writer may
# replace a sample a busy reader has not taken yet, which costs a recorder nothing: bag
# readers rebuild every state from the newest situation and the actions after it (docs/bags.md).
LATCHED = Qos(1, durability=TRANSIENT_LOCAL)
# Event streams: deep enough that a burst of 1000 rejected commands is reported in
# full, bounded so a flood cannot grow memory.
EVENTS = Qos(1000)
# Viewer-only streams (attention maps): a lost frame is harmless, a slow viewer must
# never hold up the policy.
VIEWER = Qos(5, reliability=BEST_EFFORT)

# The frame of every stamped message that shows the world (observation, world_image,
# attention maps): the gSCAN grid, cell (row 0, col 0) at the origin, x along columns, y
# along rows (so z points into the floor: the image convention), one unit per cell. The
# grid has no metric size; a robot that publishes a transform to it says how big a cell is.
GRID_FRAME = "gscan_grid"
# The observation's sensor_msgs/Image encoding: 16 one-hot uint8 channels per cell.
OBSERVATION_ENCODING = "8UC16"
EARLIER_OBSERVATION_TYPE = "std_msgs/msg/UInt8MultiArray"

# Reader depths: the newest sample only (the policy's world state), or every sample while
# busy (recorders, test probes, the policy's command graphs: each gets its report).
LATEST_DEPTH = 1
LOG_DEPTH = 1000


@dataclass(frozen=True)
class Endpoint:
    """One topic or service of the stack."""

    name: str  # relative ROS name; for a family (`attention/<word>`) its prefix
    kind: str  # TOPIC or SERVICE
    type: str  # "pkg/msg/Type" or "pkg/srv/Type"
    qos: Qos | None  # what the publisher offers (None for a service)
    recorded: bool = False  # a topic of gscan_ros bags (docs/bags.md)

    @property
    def latched(self) -> bool:
        return self.qos is not None and self.qos.latched

    @property
    def bag_topic(self) -> str:
        """The absolute name a bag stores."""
        return f"/{self.name}"


COMMAND = Endpoint("command", TOPIC, "std_msgs/msg/String", EVENTS, recorded=True)
COMMAND_GRAPH = Endpoint("command_graph", TOPIC, "std_msgs/msg/String", LATCHED, recorded=True)
STATUS = Endpoint("status", TOPIC, "std_msgs/msg/String", EVENTS, recorded=True)
# The gSCAN encoding as a 16-channel image (msg_adapters/observation.py); bags written
# before it was an image hold std_msgs/msg/UInt8MultiArray (`EARLIER_OBSERVATION_TYPE`).
OBSERVATION = Endpoint("observation", TOPIC, "sensor_msgs/msg/Image", LATCHED, recorded=True)
SITUATION = Endpoint("situation", TOPIC, "std_msgs/msg/String", LATCHED, recorded=True)
WORLD_RESET = Endpoint("world_reset", TOPIC, "std_msgs/msg/Header", LATCHED, recorded=True)
WORLD_IMAGE = Endpoint("world_image", TOPIC, "sensor_msgs/msg/Image", LATCHED, recorded=True)
ACTION = Endpoint("action", TOPIC, "std_msgs/msg/String", EVENTS, recorded=True)
# The policy's report on each episode: started, and how it ended (gscan_ros.episode_status).
EPISODE_STATUS = Endpoint("episode_status", TOPIC, "actionlib_msgs/msg/GoalStatus", EVENTS, recorded=True)
# What a bag knows of an episode beyond the live topics (split, example, dataset fields):
# JSON written by the bag writers, keyed by the episode's status id (docs/bags.md).
EPISODE = Endpoint("episode", TOPIC, "std_msgs/msg/String", EVENTS, recorded=True)
ATTENTION = Endpoint("attention", TOPIC, "sensor_msgs/msg/Image", VIEWER)  # attention/<word>
SIZE_ORDERING = Endpoint("attention/size_ordering", TOPIC, "sensor_msgs/msg/Image", VIEWER)
RESET_WORLD = Endpoint("reset_world", SERVICE, "std_srvs/srv/Trigger", None)
# Node health in the ROS convention: one DiagnosticStatus per node on the absolute
# `/diagnostics`, the name diagnostic_updater publishes on and diagnostic_aggregator reads,
# so every stack of a fleet reports on one topic (its status names are fully qualified).
# Snapshots, at 1 Hz and on each change of level: a short queue loses nothing that the next one does not say.
DIAGNOSTICS = Endpoint("/diagnostics", TOPIC, "diagnostic_msgs/msg/DiagnosticArray", Qos(10))

ENDPOINTS: tuple[Endpoint, ...] = (
    COMMAND, COMMAND_GRAPH, STATUS, OBSERVATION, SITUATION, WORLD_RESET, WORLD_IMAGE, ACTION,
    EPISODE_STATUS, EPISODE, ATTENTION, SIZE_ORDERING, RESET_WORLD, DIAGNOSTICS,
)
RECORDED: tuple[Endpoint, ...] = tuple(e for e in ENDPOINTS if e.recorded)


def topic_token(word: str) -> str:
    """A valid ROS name token for a graph word: "while spinning" -> "while_spinning", "<root>" -> "root"."""
    token = re.sub(r"[^0-9A-Za-z]+", "_", word).strip("_")
    return token if token and not token[0].isdigit() else f"w_{token}"


def attention_topic(word: str) -> str:
    """`attention/<word>`: where the policy publishes the word module's attention map."""
    return f"{ATTENTION.name}/{topic_token(word)}"


def endpoint_of(topic: str) -> Endpoint | None:
    """The table's entry for a relative or absolute topic name (family members included)."""
    name = topic.lstrip("/")
    for endpoint in ENDPOINTS:
        if endpoint.kind == TOPIC and endpoint.name.lstrip("/") == name:
            return endpoint
    if name.startswith(f"{ATTENTION.name}/"):
        return ATTENTION
    return None
