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


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda d: d["nodes"][3].update(arity=50_000_000), r"nodes\[3\]\.arity is 50000000, outside 0\.\.8"),
        (lambda d: d["nodes"][2].update(head=10**9), r"nodes\[2\]\.head is 1000000000, outside 0\.\.63"),
        (lambda d: d["nodes"][0].update(word="w" * 65), r"nodes\[0\]\.word has 65 characters"),
        (lambda d: d["edges"][0].update(label="l" * 65), r"edges\[0\]\.label has 65 characters"),
        (lambda d: d.update(command="walk " * 1000), r"command has 5000 characters"),
        (lambda d: d["nodes"].extend({"id": 10 + i, "word": "x", "module": "x", "arity": 0} for i in range(61)),
         r"has 65 nodes, more than the maximum of 64"),
        (lambda d: d.update(edges=d["edges"] * 200), r"has 600 edges, more than the maximum of 512"),
        (lambda d: d.update(nodes={"0": {}}), r"nodes: expected a list, got dict"),
    ],
)
def test_sizes_beyond_the_bounds_are_rejected_naming_the_field(mutate, message):
    d = chain().to_dict()
    mutate(d)
    with pytest.raises(GraphError, match=message):
        CommandGraph.from_dict(d)


def test_a_huge_arity_is_rejected_quickly_without_allocating_for_it():
    """The 308-byte message that took policy_node from 0.33 to 2.3 GB (validate built range(arity))."""
    import json
    import time
    import tracemalloc

    d = chain().to_dict()
    d["nodes"][3]["arity"] = 50_000_000
    text = json.dumps(d, separators=(",", ":"))
    assert len(text) < 1000  # a small message
    tracemalloc.start()
    started = time.perf_counter()
    with pytest.raises(GraphError, match="arity"):
        CommandGraph.from_json(text)
    elapsed = time.perf_counter() - started
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert peak < 1_000_000 and elapsed < 0.1


@pytest.mark.parametrize("text, message", [
    ("[" * 100_000, "nested too deeply"),
    (" " * (128 * 1024 + 1), "131073 characters, more than the maximum of 131072"),
])
def test_oversized_or_deeply_nested_json_is_a_graph_error(text, message):
    with pytest.raises(GraphError, match=message):
        CommandGraph.from_json(text)
