"""CommandGraph <-> std_msgs/String carrying the graph's versioned JSON (topic `command_graph`)."""
from __future__ import annotations

from gscan_ros.language.graph import CommandGraph
from msg_adapters.text import cdr_to_text, text_to_cdr


def graph_to_cdr(graph: CommandGraph) -> bytes:
    """The compact JSON of `graph` (schema_version included)."""
    return text_to_cdr(graph.to_json())


def cdr_to_graph(data: bytes) -> CommandGraph:
    """Parse and validate; bad JSON or an invalid graph raises GraphError naming the problem."""
    return CommandGraph.from_json(cdr_to_text(data))
