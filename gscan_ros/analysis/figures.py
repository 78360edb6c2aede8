"""The paper's Fig. 3 and Fig. 4 drawn with matplotlib (Agg), from `analysis.explain` traces.

Fig. 3 (`step_figure`): the world (`world.render`), then each word module's map from
leaves to root with the parse tree drawn above them, then the size-ordering map when
the command has a size word. Fig. 4 (`progression_figure`): one row per word, one column
per training snapshot. Every map is drawn on the grid with the objects outlined in their
colour, the agent as a black triangle and the target's cell framed with a dashed line.
Word maps use a white-to-dark scale from the map's own minimum to its maximum (darker =
attended, as in the paper; a uniform map is white); the size-ordering map a diverging
scale centred on 0 (purple: small, orange: big).
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib import patheffects  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Circle, FancyBboxPatch, Polygon, Rectangle  # noqa: E402

from gscan_ros.analysis.explain import Trace, TraceStep  # noqa: E402
from gscan_ros.language.graph import CommandGraph  # noqa: E402
from gscan_ros.world.render import COLOR_RGB, render  # noqa: E402
from gscan_ros.world.types import Situation  # noqa: E402

WORD_CMAP = "Purples"
ORDER_CMAP = "PuOr_r"  # purple = small, orange = big
SIZE_TITLE = "size ordering"
PANEL_IN = 2.0  # inches per map panel
TREE_LEVEL_IN = 0.42  # inches per parse-tree level
DPI = 100
LEGEND = ("darker = more attention (each map scaled from its own minimum to its maximum); dashed frame: "
          "the target; black triangle: the agent; outlines: the objects in their colours")
_HALO = [patheffects.withStroke(linewidth=3.2, foreground="white")]


def map_words(graph: CommandGraph) -> list[str]:
    """The graph's words from leaves to root (children before parents), each once."""
    return list(dict.fromkeys(graph.node(n).word for n in graph.postorder()))


def panel_titles(trace: Trace, t: int) -> list[str]:
    """Titles of a step figure's panels, left to right (the tests read them)."""
    step = trace.steps[t]
    return ["world"] + map_words(trace.graph) + ([SIZE_TITLE] if step.size_ordering is not None else [])


# ------------------------------------------------------------------------- drawing
def _draw_grid_items(ax, situation: Situation) -> None:
    """Object outlines, the agent and the target frame on a map panel (cell (r, c) at x=c, y=r)."""
    g = situation.grid_size
    for i in range(g + 1):
        ax.axhline(i - 0.5, color="#bbbbbb", lw=0.5, zorder=1)
        ax.axvline(i - 0.5, color="#bbbbbb", lw=0.5, zorder=1)
    for obj in situation.placed_objects:
        r, c = obj.position
        half = (0.3 + 0.15 * obj.size) / 2  # as world.render scales sizes 1-4
        colour = np.array(COLOR_RGB[obj.color]) / 255
        style = dict(fill=False, edgecolor=colour, lw=2.0, zorder=3, path_effects=_HALO)
        if obj.shape == "circle":
            patch = Circle((c, r), half, **style)
        elif obj.shape == "square":
            patch = Rectangle((c - half, r - half), 2 * half, 2 * half, **style)
        else:  # cylinder: an upright rounded can
            w = half * 0.7
            patch = FancyBboxPatch((c - w, r - half), 2 * w, 2 * half, boxstyle=f"round,pad=0,rounding_size={w * 0.6}",
                                   **style)
        ax.add_patch(patch)
    target = situation.target_object
    if target is not None:
        r, c = target.position
        for colour, style in (("white", "-"), ("black", (0, (3, 2)))):  # dashed, visible on dark cells too
            ax.add_patch(Rectangle((c - 0.45, r - 0.45), 0.9, 0.9, fill=False, edgecolor=colour, lw=1.8, ls=style,
                                   zorder=4))
    r, c = situation.agent_position
    dr, dc = situation.agent_direction.delta
    tip, left, right = (0.32, 0.0), (-0.22, -0.22), (-0.22, 0.22)
    points = [(c + px * dc - py * dr, r + px * dr + py * dc) for px, py in (tip, left, right)]
    ax.add_patch(Polygon(points, closed=True, facecolor="black", edgecolor="white", lw=1.0, zorder=5))
    ax.set_xlim(-0.5, g - 0.5)
    ax.set_ylim(g - 0.5, -0.5)
    ax.set_xticks([])
    ax.set_yticks([])


def _draw_map(ax, weights: np.ndarray | None, situation: Situation, ordering: bool = False):
    """One map on its grid; returns the image (for a colour bar) or None when there is no map."""
    image = None
    if weights is None:
        ax.set_facecolor("#eeeeee")
        ax.text(0.5, 0.5, "no map", ha="center", va="center", transform=ax.transAxes, color="#777777")
    elif ordering:
        span = float(np.abs(weights).max()) or 1.0
        image = ax.imshow(weights, cmap=ORDER_CMAP, vmin=-span, vmax=span, interpolation="nearest", zorder=0)
    else:
        lo, hi = float(weights.min()), float(weights.max())
        if hi - lo < 1e-9:  # uniform: nothing attended, drawn white
            hi = lo + 1.0
        image = ax.imshow(weights, cmap=WORD_CMAP, vmin=lo, vmax=hi, interpolation="nearest", zorder=0)
    _draw_grid_items(ax, situation)
    return image


def _draw_world(ax, situation: Situation) -> None:
    g = situation.grid_size
    ax.imshow(render(situation, cell_px=40), extent=(-0.5, g - 0.5, g - 0.5, -0.5), interpolation="nearest")
    ax.set_xticks([])
    ax.set_yticks([])


def _colour_bar(fig: Figure, ax, image, ordering: bool) -> None:
    box = ax.get_position()
    cax = fig.add_axes((box.x0 + 0.1 * box.width, box.y0 - 0.075 * box.height, 0.8 * box.width, 0.05 * box.height))
    bar = fig.colorbar(image, cax=cax, orientation="horizontal")
    lo, hi = image.get_clim()
    bar.set_ticks([lo, hi])
    bar.set_ticklabels(["small", "big"] if ordering else [f"{lo:.3f}", f"{hi:.3f}"])
    bar.ax.tick_params(labelsize=7, length=2, pad=1)
    if ordering:
        bar.ax.set_xlabel("(-att_small + att_big) / 2", fontsize=7, labelpad=-6)


def _draw_tree(fig: Figure, graph: CommandGraph, centres: dict[str, tuple[float, float]], level_h: float) -> None:
    """The parse above the map panels: each node over its panel, one level per height."""
    height: dict[int, int] = {}
    for n in graph.postorder():
        children = graph.children(n)
        height[n] = 1 + max(height[c] for c in children) if children else 0
    pos = {n: (centres[graph.node(n).word][0], centres[graph.node(n).word][1] + height[n] * level_h)
           for n in graph.postorder()}
    for e in graph.edges:
        (x0, y0), (x1, y1) = pos[e.parent], pos[e.child]
        fig.add_artist(Line2D([x0, x1], [y0, y1], transform=fig.transFigure, color="#666666", lw=1.2, zorder=1))
        fig.text((x0 + x1) / 2, (y0 + y1) / 2, e.label, fontsize=7, color="#555555", ha="center", va="center",
                 style="italic", path_effects=_HALO)
    for n, (x, y) in pos.items():
        node = graph.node(n)
        label = node.word if node.module == node.word else f"{node.word}\n[{node.module}]"
        fig.text(x, y, label, ha="center", va="center", fontsize=9, zorder=2,
                 bbox=dict(boxstyle="round,pad=0.3", facecolor="#fff8e6", edgecolor="#aa8844"))


# ----------------------------------------------------------------------- figures
def step_figure(trace: Trace, t: int, title: str = "") -> Figure:
    """Fig. 3 for step `t` of `trace` (see the module docstring)."""
    step = trace.steps[t]
    words = map_words(trace.graph)
    order = step.size_ordering
    ncols = 1 + len(words) + (order is not None)
    levels = len(trace.graph.levels())
    title_in, label_in, bar_in, margin_in, space_in = 0.55, 0.35, 0.55, 0.2, 0.3
    width_in = ncols * PANEL_IN + (ncols - 1) * space_in + 2 * margin_in
    height_in = title_in + levels * TREE_LEVEL_IN + label_in + PANEL_IN + bar_in
    fig = plt.figure(figsize=(width_in, height_in), dpi=DPI)
    grid = fig.add_gridspec(1, ncols, left=margin_in / width_in, right=1 - margin_in / width_in,
                            bottom=bar_in / height_in, top=(bar_in + PANEL_IN) / height_in, wspace=space_in / PANEL_IN)
    axes = [fig.add_subplot(grid[0, i]) for i in range(ncols)]
    _draw_world(axes[0], step.situation)
    axes[0].set_title("world", fontsize=10, fontweight="bold")
    axes[0].set_xlabel(f"t={t}, next: {step.action.token}", fontsize=9)
    centres = {}
    for ax, word in zip(axes[1:], words):
        image = _draw_map(ax, step.attention.get(word), step.situation)
        ax.set_title(word, fontsize=10, fontweight="bold")
        if image is not None:
            _colour_bar(fig, ax, image, ordering=False)
        box = ax.get_position()
        centres[word] = ((box.x0 + box.x1) / 2, box.y1 + (label_in + TREE_LEVEL_IN / 2) / height_in)
    if order is not None:
        ax = axes[-1]
        image = _draw_map(ax, order, step.situation, ordering=True)
        ax.set_title(SIZE_TITLE, fontsize=10, fontweight="bold")
        _colour_bar(fig, ax, image, ordering=True)
    _draw_tree(fig, trace.graph, centres, TREE_LEVEL_IN / height_in)
    fig.suptitle(title or trace.graph.command, fontsize=12, y=1 - 0.08 / height_in, va="top")
    fig.text(0.5, 1 - 0.36 / height_in, LEGEND, ha="center", va="top", fontsize=8, color="#444444")
    return fig


def progression_figure(columns: Sequence[tuple[str, TraceStep]], graph: CommandGraph, title: str = "",
                       subtitle: str = "") -> Figure:
    """Fig. 4: one row per word (leaves to root, then the size ordering when every column has
    one), one column per (label, step), the world of the first column on the left. Each map
    notes its maximum: a near-uniform map (max about 1/cells) attends nowhere."""
    words = map_words(graph)
    rows = words + ([SIZE_TITLE] if all(s.size_ordering is not None for _, s in columns) else [])
    cell_in, label_in, head_in = 1.5, 1.3, 1.15
    ncols = 1 + len(columns)
    width_in, height_in = label_in + ncols * cell_in * 1.06 + 0.1, head_in + len(rows) * cell_in * 1.06 + 0.1
    fig = plt.figure(figsize=(width_in, height_in), dpi=DPI)
    grid = fig.add_gridspec(len(rows), ncols, left=label_in / width_in, right=1 - 0.1 / width_in,
                            bottom=0.1 / height_in, top=1 - head_in / height_in, wspace=0.06, hspace=0.06)
    world_ax = fig.add_subplot(grid[0, 0])
    _draw_world(world_ax, columns[0][1].situation)
    world_ax.set_title("world", fontsize=10, fontweight="bold")
    for r, name in enumerate(rows):
        box = grid[r, 0].get_position(fig)
        fig.text(0.5 * label_in / width_in, (box.y0 + box.y1) / 2, name, ha="center", va="center", fontsize=10,
                 fontweight="bold", wrap=True)
        for c, (label, step) in enumerate(columns, start=1):
            ax = fig.add_subplot(grid[r, c])
            weights = step.size_ordering if name == SIZE_TITLE else step.attention.get(name)
            _draw_map(ax, weights, step.situation, ordering=name == SIZE_TITLE)
            if weights is not None and name != SIZE_TITLE:
                ax.text(0.97, 0.03, f"max {float(np.max(weights)):.2f}", transform=ax.transAxes, ha="right",
                        va="bottom", fontsize=7, zorder=6, path_effects=_HALO)
            if r == 0:
                ax.set_title(label, fontsize=9)
    fig.suptitle(title or graph.command, fontsize=12, y=1 - 0.08 / height_in, va="top")
    fig.text(0.5, 1 - 0.36 / height_in, subtitle or "word maps along training", ha="center", va="top", fontsize=8,
             color="#444444", wrap=True)
    return fig


def figure_rgb(fig: Figure) -> np.ndarray:
    """The figure as RGB uint8[H, W, 3] (for GIF frames)."""
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()


def save_figure(fig: Figure, path: str | Path) -> Path:
    path = Path(path)
    fig.savefig(path, dpi=DPI, facecolor="white")
    plt.close(fig)
    return path
