"""`gscan-ros explain`: the numbers on hand-built cases, the maps of the shipped model, the
Fig. 3 panels and the Foxglove layout."""
import json
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from PIL import Image  # noqa: E402

from gscan_ros.analysis.explain import (  # noqa: E402
    Reading,
    noun_colours,
    noun_colours_table,
    peak_distance,
    referent_word,
    size_correlation,
    size_heads,
    size_heads_table,
    size_ordering,
    size_word_first,
    spearman,
    step0_readings,
    summarize,
    trace,
    weakest_colour,
    with_referent,
)
from gscan_ros.analysis.figures import DPI, TREE_LEVEL_IN, panel_titles, step_figure  # noqa: E402
from gscan_ros.cli import main  # noqa: E402
from gscan_ros.data.sources import sample_episode  # noqa: E402
from gscan_ros.language import get_parser  # noqa: E402
from gscan_ros.model.policy import Policy  # noqa: E402
from gscan_ros.world import World  # noqa: E402
from gscan_ros.world.types import Heading, Position, Situation, WorldObject  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def policy():
    return Policy.from_checkpoint()


# ------------------------------------------------------------------ hand-computed numbers
def circle(size, row, col, color="red"):
    return WorldObject("circle", color, size, Position(row, col))


def situation(objects, target):
    return Situation(Position(5, 5), Heading.EAST, tuple(objects), target_object=target)


def test_spearman_matches_hand_computed_values():
    assert spearman([1, 2, 3, 4], [1, 3, 2, 4]) == pytest.approx(0.8)  # 1 - 6*2/(4*15)
    assert spearman([1, 2, 2, 3], [1, 2, 3, 4]) == pytest.approx(3 / math.sqrt(10))  # tied ranks 2.5, 2.5
    assert spearman([3, 2, 1], [1, 2, 3]) == pytest.approx(-1.0)
    assert math.isnan(spearman([1, 1, 1], [1, 2, 3])) and math.isnan(spearman([1], [1]))


def test_size_ordering_is_big_minus_small_over_two():
    a, b = np.eye(6, dtype=np.float32), np.full((6, 6), 0.5, dtype=np.float32)
    np.testing.assert_allclose(size_ordering({"small": a}, {"small": b}), (b - a) / 2)  # b: the big head
    np.testing.assert_allclose(size_ordering({"big": a, "walk": b}, {"big": b}), (a - b) / 2)
    assert size_ordering({"red": a}, {}) is None
    assert size_ordering({"small": a}, {}) is None  # big and small in separate modules: no antonym head


def test_localization_and_size_correlation_on_a_hand_built_case():
    """Three episodes whose numbers are worked out by hand: test has a hit (rho 0.5) and a
    miss (no size word), visual a hit whose size ordering is flat (rho undefined)."""
    objects = [circle(1, 0, 0), circle(2, 0, 1), circle(4, 0, 2), WorldObject("square", "blue", 3, Position(3, 3))]
    small_target, big_target = situation(objects, objects[0]), situation(objects, objects[2])
    peak_at = lambda r, c: np.pad([[1.0]], ((r, 5 - r), (c, 5 - c)))  # noqa: E731
    ordering = np.zeros((6, 6))
    ordering[0, :3] = [-0.3, 0.1, 0.05]  # ranks 1, 3, 2 against sizes 1, 2, 4: rho = 1 - 6*2/(3*8) = 0.5
    ordering[3, 3] = 9.0  # the square is not a circle: ignored
    readings = [  # the nouns' maps: one on a circle, one on the square (the wrong shape), one missing
        Reading("test", "walk to a small circle", small_target, peak_at(0, 0), ordering, peak_at(0, 2)),
        Reading("test", "walk to a circle", big_target, peak_at(0, 1), None, peak_at(3, 3)),
        Reading("visual", "walk to a big circle", big_target, peak_at(0, 2), np.zeros((6, 6))),
    ]
    assert peak_distance(peak_at(0, 0), objects[0]) == 0 and peak_distance(peak_at(0, 1), objects[2]) != 0
    assert peak_distance(peak_at(0, 1), objects[2]) == 1 and peak_distance(peak_at(3, 3), objects[0]) == 6
    assert size_correlation(ordering, small_target, "circle") == pytest.approx(0.5)
    s = summarize(readings)
    assert list(s) == ["test", "visual", "all"]
    assert math.isnan(s["test"].pop("size_word_first"))  # no size word's map given
    assert s["test"] == {"episodes": 2, "localization": 50.0, "localization_chance": 25.0, "beside": 50.0,
                         "on_agent": 0.0, "noun_on_shape": 50.0, "size_episodes": 1,
                         "size_spearman": pytest.approx(0.5)}
    on_agent = summarize([Reading("test", "walk to a circle", big_target, peak_at(5, 5), None)])["test"]
    assert on_agent["on_agent"] == 100.0 and on_agent["localization"] == 0.0  # the agent stands at (5, 5)
    assert s["visual"]["localization"] == 100.0 and s["visual"]["size_episodes"] == 0
    assert math.isnan(s["visual"]["size_spearman"]) and math.isnan(s["visual"]["noun_on_shape"])
    assert s["all"]["localization"] == pytest.approx(200 / 3) and s["all"]["size_spearman"] == pytest.approx(0.5)


def test_size_word_first_compares_the_target_with_the_objects_the_command_names():
    """Worked by hand: "small" is relative to the objects of the command's name (its
    shape, and its colour when given), so a smaller circle of another colour does not
    count against a coloured command; a map that prefers the next size up is a miss."""
    tiny_blue, two_red, three_red = circle(1, 0, 0, "blue"), circle(2, 0, 1), circle(3, 0, 2)
    scene = situation([tiny_blue, two_red, three_red], two_red)
    ordered, confused = np.zeros((6, 6)), np.zeros((6, 6))
    ordered[0, :3] = [0.9, 0.6, 0.2]  # by size: blue 1 first, then red 2
    confused[0, :3] = [0.1, 0.3, 0.4]  # the size-3 circle above the size-2 target
    lone = situation([two_red, WorldObject("square", "red", 1, Position(3, 3))], two_red)
    reading = lambda command, sit, m: Reading("test", command, sit, None, None, None,  # noqa: E731
                                              None if m is None else {"small": m, "big": np.zeros((6, 6))})
    assert size_word_first(reading("walk to a red small circle", scene, ordered)) is True
    assert size_word_first(reading("walk to a small circle", situation(scene.placed_objects, tiny_blue),
                                    ordered)) is True
    assert size_word_first(reading("walk to a red small circle", scene, confused)) is False
    assert size_word_first(reading("walk to a small circle", lone, ordered)) is None  # no other circle
    assert size_word_first(reading("walk to a circle", scene, None)) is None
    s = summarize([reading("walk to a red small circle", scene, ordered),
                   reading("walk to a red small circle", scene, confused),
                   reading("walk to a small circle", lone, ordered)])["test"]
    assert s["size_word_first"] == 50.0
    flat = reading("walk to a red small circle", scene, np.full((6, 6), 1 / 36))
    assert size_word_first(flat) is False  # a flat map ranks nothing first
    heads = size_heads([reading("walk to a red small circle", scene, ordered), flat,
                        reading("walk to a circle", scene, None)])
    assert heads == {"small": (2, pytest.approx(0.45)), "big": (2, 0.0)}
    assert size_heads_table(heads).splitlines()[2:] == ["| small | 2 | 0.45 |", "| big | 2 | 0 |"]


def test_noun_colours_rank_each_colour_against_the_best_object_of_the_shape():
    """Two scenes worked out by hand: the red circle gets 0.2 and 0.5 of the best circle's
    value, the blue one is the best in both; a scene with one circle counts for nothing."""
    red, blue, green = circle(1, 0, 0, "red"), circle(2, 0, 1, "blue"), circle(3, 0, 2, "green")
    noun = np.zeros((6, 6))
    noun[0, :3] = [0.1, 0.5, 0.25]
    noun2 = np.zeros((6, 6))
    noun2[0, :2] = [0.2, 0.4]
    lone = situation([red, WorldObject("square", "red", 2, Position(3, 3))], red)
    readings = [
        Reading("test", "walk to a circle", situation([red, blue, green], blue), None, None, noun),
        Reading("visual", "walk to a blue circle", situation([red, blue], blue), None, None, noun2),
        Reading("test", "walk to a circle", lone, None, None, noun),
        Reading("test", "walk to a circle", situation([red, blue], blue), None, None, None),  # no noun map
    ]
    found = noun_colours(readings)
    assert list(found) == ["circle"]
    assert found["circle"]["red"] == (2, pytest.approx((0.2 + 0.5) / 2))
    assert found["circle"]["blue"] == (2, pytest.approx(1.0))
    assert found["circle"]["green"] == (1, pytest.approx(0.5))
    assert noun_colours_table(found).splitlines()[2] == "| circle | 1.00 (2) | 0.50 (1) | 0.35 (2) |"
    assert weakest_colour(found) == ("circle", "red", pytest.approx(0.35)) and weakest_colour({}) is None


@pytest.mark.parametrize("parser, command, word", [
    ("semantic", "walk to a yellow small circle while spinning", "yellow"),
    ("constituency", "pull a red big square cautiously", "NP"),
    ("dependency", "pull a red big square cautiously", "square"),
    ("semantic", "push a cylinder", "cylinder"),
])
def test_the_noun_phrase_map_is_the_highest_node_below_the_verb(parser, command, word):
    assert referent_word(get_parser(parser).parse(command)) == word


# ------------------------------------------------------------------------ the shipped model
def test_policy_steps_carry_the_antonym_heads_map_for_a_size_word(policy):
    world = World(sample_episode(3, command="walk to a small circle").situation).encode()
    policy.reset(policy.parse("walk to a small circle"))
    out = policy.step(world)
    assert set(out.antonyms) == {"small"} and out.antonyms["small"].shape == (6, 6)
    assert not np.allclose(out.antonyms["small"], out.attention["small"])  # the other head
    policy.reset(policy.parse("walk to a red circle"))
    assert policy.step(world).antonyms == {}


def test_batched_step0_readings_equal_the_single_episode_trace(policy):
    episodes = [sample_episode(seed, command="walk to a yellow small circle while spinning") for seed in (3, 4)]
    readings = step0_readings(policy, episodes, batch_size=2)
    for ep, reading in zip(episodes, readings):
        step = trace(policy, ep.situation, ep.command, until=0).steps[0]
        np.testing.assert_allclose(reading.referent, step.attention["yellow"], atol=1e-6)
        np.testing.assert_allclose(reading.ordering, step.size_ordering, atol=1e-6)


def test_step0_readings_refuse_an_episode_on_another_grid(policy):
    """The model reads one grid size: an episode on another is named, not an index error."""
    from gscan_ros.errors import GscanError

    episodes = [sample_episode(3, command="walk to a circle"), sample_episode(4, 8, "walk to a circle")]
    with pytest.raises(GscanError, match=r"is on a 8x8 grid; the model was trained on 6x6"):
        step0_readings(policy, episodes)


# ------------------------------------------------------------------------------- figures
@pytest.mark.parametrize("command, panels", [
    ("walk to a yellow small circle while spinning",
     ["world", "circle", "small", "yellow", "walk", "while spinning", "size ordering"]),
    ("push a big square", ["world", "square", "big", "push", "size ordering"]),
    ("pull a green cylinder hesitantly", ["world", "cylinder", "green", "pull", "hesitantly"]),
    ("walk to a circle", ["world", "circle", "walk"]),
])
def test_step_figure_has_one_panel_per_word_and_the_size_ordering(policy, command, panels):
    ep = sample_episode(1, command=command)
    tr = trace(policy, with_referent(ep.situation, command), command, until=0)
    assert panel_titles(tr, 0) == panels
    fig = step_figure(tr, 0)
    try:
        assert [ax.get_title() for ax in fig.axes if ax.get_title()] == panels
        assert len(fig.axes) == 2 * len(panels) - 1  # a colour bar under every map
    finally:
        plt.close(fig)


def test_explain_writes_a_png_with_the_panels(tmp_path, capsys):
    out, small = tmp_path / "fig3.png", tmp_path / "three_panels.png"
    assert main(["explain", "walk to a yellow small circle while spinning", "--seed", "3", "--out", str(out),
                 "--threads", "1"]) == 0
    assert "panels: world, circle, small, yellow, walk, while spinning, size ordering" in capsys.readouterr().out
    assert main(["explain", "walk to a circle", "--seed", "3", "--out", str(small)]) == 0
    assert "panels: world, circle, walk\n" in capsys.readouterr().out
    (width, height), (width3, height3) = Image.open(out).size, Image.open(small).size
    assert width > 2 * width3 and height == height3 + TREE_LEVEL_IN * DPI * 3  # 7 vs 3 panels; 5 vs 2 levels
    assert main(["explain", "walk to a circle", "--seed", "3", "--out", str(out)]) == 1  # no silent overwrite
    assert "--overwrite" in capsys.readouterr().err


def test_explain_gif_has_one_frame_per_decoding_step(tmp_path, policy):
    command, out = "walk to a big circle", tmp_path / "steps.gif"
    ep = sample_episode(2, command=command)
    steps = len(trace(policy, ep.situation, command).steps)
    assert main(["explain", command, "--seed", "2", "--gif", "--out", str(out), "--threads", "1"]) == 0
    assert Image.open(out).n_frames == steps


def test_explain_loads_the_model_on_the_device_auto_names(tmp_path):
    """'auto' is a launcher's name (cuda if torch sees a GPU, else cpu): explain resolves it
    before the model loads, as torch knows no device 'auto'."""
    out = tmp_path / "auto.png"
    assert main(["explain", "walk to a circle", "--seed", "3", "--out", str(out), "--device", "auto"]) == 0
    assert out.is_file()


def test_explain_situation_file_and_step(tmp_path, capsys):
    ep = sample_episode(5, command="push a green cylinder hesitantly")
    path = tmp_path / "situation.json"
    path.write_text(json.dumps({"situation": ep.situation.to_json()}))
    out = tmp_path / "t2.png"
    assert main(["explain", ep.command, "--situation", str(path), "--step", "2", "--out", str(out)]) == 0
    assert "step 2 (next:" in capsys.readouterr().out and out.stat().st_size > 0


@pytest.mark.parametrize("argv, message", [
    (["--metrics"], "--metrics needs --data"),
    (["walk to a circle", "--gif", "--out", "x.png"], "--gif writes a .gif"),
    (["walk to a circle"], "--out FILE"),
    (["--situation", "setup.py", "--out", "x.png"], "--situation needs a COMMAND"),
    (["walk to a circle", "--step", "500", "--out", "x.png"], "--step must be at most"),
    (["walk to a circle", "--step", "2", "--out", "x.gif"], "--step draws one step as a .png"),
    (["--progression", ".", "--checkpoint", "setup.py", "--out", "x.png"], "it takes no --checkpoint"),
    (["--metrics", "--data", "setup.py", "--progression", ".", "--checkpoint", "setup.py"], "it takes no --checkpoint"),
    (["walk to a circle", "--progression", ".", "--out", "x.png"], "no step_<N>.pt snapshots"),
    (["circle the walk", "--out", "x.png"], "not a gSCAN command"),
])
def test_bad_arguments_are_one_line_errors(tmp_path, monkeypatch, capsys, argv, message):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "setup.py").write_text("")
    assert main(["explain", *argv]) == 1
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


# ----------------------------------------------------------------------------- live view
def test_foxglove_layout_names_only_topics_the_stack_publishes():
    """Every topic in config/foxglove_layout.json is the world image, action, status, the
    size ordering or the attention topic of a word in the semantic parse of a gSCAN command."""
    from gscan_ros.data.commands import COMMANDS
    from gscan_ros.nodes import common

    parser = get_parser("semantic")
    words = {n.word for c in COMMANDS for n in parser.parse(c.text).nodes}
    published = {common.WORLD_IMAGE, common.ACTION, common.STATUS, common.SIZE_ORDERING}
    published |= {f"{common.ATTENTION_PREFIX}/{common.topic_token(w)}" for w in words}

    def topics(node):
        if isinstance(node, dict):
            for key, value in node.items():
                if key in ("imageTopic", "topicPath"):
                    yield value
                else:
                    yield from topics(value)
        elif isinstance(node, list):
            for item in node:
                yield from topics(item)

    layout = json.loads((ROOT / "config" / "foxglove_layout.json").read_text())
    named = [t.lstrip("/") for t in topics(layout["configById"])]
    assert common.WORLD_IMAGE in named and common.SIZE_ORDERING in named
    assert set(named) <= published
    assert {f"{common.ATTENTION_PREFIX}/{common.topic_token(w)}" for w in words} <= set(named)  # every word

    def panels(node):
        return [node] if isinstance(node, str) else panels(node["first"]) + panels(node["second"])

    shown = panels(layout["layout"]) + [p for tab in layout["configById"]["Tab!words"]["tabs"]
                                        for p in panels(tab["layout"])]
    assert sorted(shown) == sorted(layout["configById"])  # every configured panel is placed, once
