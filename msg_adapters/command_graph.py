"""CommandGraph <-> std_msgs/String carrying the graph's versioned JSON (topic `command_graph`)."""
from __future__ import annotations

from std_msgs.msg import String

from gscan_ros.language.graph import CommandGraph
from msg_adapters.errors import MessageFormatError


def graph_to_msg(graph: CommandGraph) -> String:
    """The compact JSON of `graph` (schema_version included)."""
    return String(data=graph.to_json())


def msg_to_graph(msg: String) -> CommandGraph:
    """Parse and validate; bad JSON or an invalid graph raises GraphError naming the problem."""
    data = getattr(msg, "data", None)
    if not isinstance(data, str):
        raise MessageFormatError(f"expected a std_msgs/String with JSON data, got {type(msg).__name__}")
    return CommandGraph.from_json(data)
