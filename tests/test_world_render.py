"""Renderer: sizes, colors where the state says, frames, attention panels, files."""
import numpy as np
import pytest
from PIL import Image

from gscan_ros.errors import InvalidActionError
from gscan_ros.world import Heading, Position, Situation, World, WorldObject, demonstrate
from gscan_ros.world.render import COLOR_RGB, render, render_frames, save_gif, save_png

P = Position
CELL = 40


def _situation():
    objs = (WorldObject("square", "red", 4, P(0, 0)), WorldObject("circle", "blue", 2, P(3, 4)),
            WorldObject("cylinder", "green", 3, P(5, 5)))
    return Situation(P(2, 1), Heading.EAST, objs, objs[1])


def _cell(img, row, col):
    return img[row * CELL + 1:(row + 1) * CELL, col * CELL + 1:(col + 1) * CELL]


def _has(region, rgb):
    return bool(np.all(region == np.array(rgb, dtype=np.uint8), axis=-1).any())


def test_render_draws_objects_and_agent_where_the_state_says():
    img = render(_situation(), cell_px=CELL)
    assert img.shape == (6 * CELL + 1, 6 * CELL + 1, 3) and img.dtype == np.uint8
    assert _has(_cell(img, 0, 0), COLOR_RGB["red"]) and _has(_cell(img, 3, 4), COLOR_RGB["blue"])
    assert _has(_cell(img, 5, 5), COLOR_RGB["green"])
    assert not _has(_cell(img, 1, 1), COLOR_RGB["red"])
    agent = _cell(img, 2, 1)
    assert (agent.astype(int).sum(axis=-1) < 100).mean() > 0.08  # dark triangle
    assert (_cell(img, 2, 2).astype(int).sum(axis=-1) < 100).mean() == 0


def test_agent_triangle_points_along_the_heading():
    def reach(heading):
        """How far the dark triangle extends from the cell centre towards +row, -row, +col, -col."""
        s = Situation(P(2, 2), heading, ())
        ys, xs = np.nonzero(_cell(render(s, cell_px=CELL), 2, 2).astype(int).sum(axis=-1) < 100)
        centre = (CELL - 2) / 2
        return {Heading.SOUTH: ys.max() - centre, Heading.NORTH: centre - ys.min(),
                Heading.EAST: xs.max() - centre, Heading.WEST: centre - xs.min()}

    for heading in Heading:
        extents = reach(heading)
        assert max(extents, key=extents.get) is heading  # the tip is the farthest point


def test_object_size_scales_the_shape():
    def area(size):
        s = Situation(P(5, 0), Heading.EAST, (WorldObject("square", "yellow", size, P(0, 0)),))
        return int(np.all(_cell(render(s, cell_px=CELL), 0, 0) == COLOR_RGB["yellow"], axis=-1).sum())

    areas = [area(k) for k in (1, 2, 3, 4)]
    assert areas == sorted(areas) and areas[0] < areas[3] / 2


def test_world_render_matches_render_of_its_state():
    w = World(_situation())
    w.step("walk")
    np.testing.assert_array_equal(render(w), render(w.snapshot()))


def test_render_frames_with_attention_panels():
    s = _situation()
    actions = demonstrate(s, "walk to a circle")
    rng = np.random.default_rng(0)
    attention = [{"walk": rng.random((6, 6)), "circle": rng.random((6, 6))} for _ in range(len(actions) + 1)]
    frames = render_frames(s, actions, attention, cell_px=CELL)
    assert len(frames) == len(actions) + 1
    assert len({f.shape for f in frames}) == 1
    plain = render_frames(s, actions, cell_px=CELL)
    assert frames[0].shape[1] > 2.5 * plain[0].shape[1]  # two panels beside the grid
    assert frames[0].shape[0] > plain[0].shape[0]  # panels carry a word label above the map
    assert not np.array_equal(frames[0], frames[1])


def test_render_frames_handles_trailing_eos_only():
    s = _situation()
    assert len(render_frames(s, ["walk", "<eos>"], cell_px=20)) == 2
    with pytest.raises(InvalidActionError):
        render_frames(s, ["<eos>", "walk"], cell_px=20)


def test_save_png_and_gif(tmp_path):
    s = _situation()
    frames = render_frames(s, demonstrate(s, "walk to a circle"), cell_px=20)
    png = save_png(frames[0], tmp_path / "f.png")
    assert np.array_equal(np.asarray(Image.open(png).convert("RGB")), frames[0])
    gif = save_gif(frames, tmp_path / "a.gif", fps=5)
    with Image.open(gif) as im:
        assert im.n_frames == len(frames) and im.info["duration"] == 200
