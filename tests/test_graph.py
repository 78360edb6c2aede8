import pytest

from gscan_ros.errors import GraphError
from gscan_ros.language.graph import CommandGraph, GraphEdge, GraphNode


def chain() -> CommandGraph:
    nodes = [GraphNode(0, "while spinning", "while spinning", 1), GraphNode(1, "walk", "walk", 1),
             GraphNode(2, "small", "big|small", 1, head=1), GraphNode(3, "circle", "circle", 0)]
    edges = [GraphEdge(0, 1, "arg", 0), GraphEdge(1, 2, "arg", 0), GraphEdge(2, 3, "arg", 0)]
    return CommandGraph.build("walk to a small circle while spinning", "semantic", nodes, edges, 0)


def test_postorder_and_levels():
    g = chain()
    assert g.postorder() == (3, 2, 1, 0)
    assert g.levels() == ((3,), (2,), (1,), (0,))
    assert g.modules() == ("big|small", "circle", "walk", "while spinning")


def test_json_round_trip():
    g = chain()
    assert CommandGraph.from_json(g.to_json()) == g


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda d: d.update(schema_version=99), "schema_version"),
        (lambda d: d.update(root=42), "root 42"),
        (lambda d: d["edges"].append({"parent": 3, "child": 0, "label": "arg", "slot": 0}), "arity 0"),
        (lambda d: d["nodes"][1].update(arity=2), "arity 2"),
        (lambda d: d["nodes"].append({"id": 9, "word": "x", "module": "x", "arity": 0}), "not reachable"),
        (lambda d: d.pop("nodes"), "malformed"),
    ],
)
def test_invalid_graphs_are_rejected(mutate, message):
    d = chain().to_dict()
    mutate(d)
    with pytest.raises(GraphError, match=message):
        CommandGraph.from_dict(d)


def test_garbage_json():
    with pytest.raises(GraphError, match="not valid JSON"):
        CommandGraph.from_json("{nope")
