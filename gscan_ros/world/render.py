"""RGB pictures of the gSCAN world (Pillow), for `world_image`, `gscan-ros render` and GIFs.

Drawn from the state, not from the 16-channel encoding: white cells with grey grid
lines, objects as filled shapes scaled by size 1-4 (square, circle, and a cylinder
drawn as an upright can), the agent as a dark triangle pointing along its heading
(drawn on top, so it stays visible on an object's cell). `render_frames` replays
actions through `World` and can put one attention panel per word beside the grid.
"""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from gscan_ros.errors import InvalidActionError
from gscan_ros.world.types import Action, Heading, Situation, WorldObject
from gscan_ros.world.world import World

COLOR_RGB: dict[str, tuple[int, int, int]] = {
    "red": (214, 39, 40),
    "green": (44, 160, 44),
    "yellow": (240, 190, 20),
    "blue": (31, 100, 200),
}
BACKGROUND = (255, 255, 255)
GRID_LINE = (170, 170, 170)
TARGET_CELL = (255, 244, 214)
AGENT_FILL = (30, 30, 30)
AGENT_EDGE = (255, 255, 255)
CAPTION_BG = (245, 245, 245)
TEXT = (20, 20, 20)
PANEL_GAP = 8


@lru_cache(maxsize=8)
def _font(px: int) -> ImageFont.ImageFont:
    return ImageFont.load_default(size=px)


def _darker(rgb: tuple[int, int, int], f: float = 0.6) -> tuple[int, int, int]:
    return tuple(int(c * f) for c in rgb)


def _lighter(rgb: tuple[int, int, int], f: float = 0.45) -> tuple[int, int, int]:
    return tuple(int(c + (255 - c) * f) for c in rgb)


def _draw_object(draw: ImageDraw.ImageDraw, obj: WorldObject, x0: int, y0: int, cell: int) -> None:
    extent = cell * (0.3 + 0.15 * obj.size)  # size 1 -> 45 % of the cell, 4 -> 90 %
    cx, cy = x0 + cell / 2, y0 + cell / 2
    fill = COLOR_RGB[obj.color]
    edge = _darker(fill)
    width = max(1, cell // 30)
    half = extent / 2
    if obj.shape == "square":
        draw.rectangle((cx - half, cy - half, cx + half, cy + half), fill=fill, outline=edge, width=width)
    elif obj.shape == "circle":
        draw.ellipse((cx - half, cy - half, cx + half, cy + half), fill=fill, outline=edge, width=width)
    else:  # cylinder: upright can, elliptic top lighter than the body
        w, cap = half * 0.7, extent * 0.14
        top, bottom = cy - half + cap, cy + half - cap
        draw.ellipse((cx - w, bottom - cap, cx + w, bottom + cap), fill=fill, outline=edge, width=width)
        draw.rectangle((cx - w, top, cx + w, bottom), fill=fill)
        draw.line((cx - w, top, cx - w, bottom), fill=edge, width=width)
        draw.line((cx + w, top, cx + w, bottom), fill=edge, width=width)
        draw.ellipse((cx - w, top - cap, cx + w, top + cap), fill=_lighter(fill), outline=edge, width=width)


def _draw_agent(draw: ImageDraw.ImageDraw, heading: Heading, x0: int, y0: int, cell: int) -> None:
    cx, cy, r = x0 + cell / 2, y0 + cell / 2, cell * 0.36
    # Triangle pointing east, rotated to the heading (rows grow southward).
    tip, back_l, back_r = (r, 0.0), (-0.7 * r, -0.75 * r), (-0.7 * r, 0.75 * r)
    dr, dc = heading.delta
    points = [(cx + px * dc - py * dr, cy + px * dr + py * dc) for px, py in (tip, back_l, back_r)]
    draw.polygon(points, fill=AGENT_FILL, outline=AGENT_EDGE, width=max(1, cell // 20))


def _grid_image(world: World, cell: int, highlight_target: bool) -> Image.Image:
    n = world.grid_size
    side = n * cell + 1
    img = Image.new("RGB", (side, side), BACKGROUND)
    draw = ImageDraw.Draw(img)
    target = world.target if highlight_target else None
    if target is not None:
        r, c = target.position
        draw.rectangle((c * cell, r * cell, (c + 1) * cell, (r + 1) * cell), fill=TARGET_CELL)
    for i in range(n + 1):
        draw.line((0, i * cell, n * cell, i * cell), fill=GRID_LINE)
        draw.line((i * cell, 0, i * cell, n * cell), fill=GRID_LINE)
    for obj in world.objects:
        _draw_object(draw, obj, obj.position.col * cell, obj.position.row * cell, cell)
    row, col = world.agent_position
    _draw_agent(draw, world.agent_direction, col * cell, row * cell, cell)
    return img


def render(world_or_situation: World | Situation, cell_px: int = 40, highlight_target: bool = True) -> np.ndarray:
    """RGB uint8[H, W, 3] of a world or situation; H = W = grid_size * cell_px + 1.

    The target's cell (if the situation names one) gets a pale background.
    """
    world = world_or_situation if isinstance(world_or_situation, World) else World(world_or_situation)
    return np.asarray(_grid_image(world, cell_px, highlight_target))


def _attention_panel(weights: np.ndarray | None, word: str, world: World, cell: int) -> Image.Image:
    """One word's 6x6 map, min-max scaled, white (0) to dark red (max); agent cell boxed."""
    n = world.grid_size
    side = n * cell + 1
    label_h = max(12, cell // 3) + 4
    panel = Image.new("RGB", (side, side + label_h), BACKGROUND)
    draw = ImageDraw.Draw(panel)
    if weights is not None:
        w = np.asarray(weights, dtype=np.float64).reshape(n, n)
        span = w.max() - w.min()
        scaled = (w - w.min()) / span if span > 0 else np.zeros_like(w)
        for r in range(n):
            for c in range(n):
                v = scaled[r, c]
                rgb = (255, int(255 - 200 * v), int(255 - 220 * v))
                draw.rectangle((c * cell, label_h + r * cell, (c + 1) * cell, label_h + (r + 1) * cell), fill=rgb)
    for i in range(n + 1):
        draw.line((0, label_h + i * cell, n * cell, label_h + i * cell), fill=GRID_LINE)
        draw.line((i * cell, label_h, i * cell, label_h + n * cell), fill=GRID_LINE)
    row, col = world.agent_position
    draw.rectangle((col * cell + 1, label_h + row * cell + 1, (col + 1) * cell - 1, label_h + (row + 1) * cell - 1),
                   outline=AGENT_FILL, width=max(1, cell // 20))
    draw.text((2, 1), word if weights is not None else f"{word} (-)", fill=TEXT, font=_font(label_h - 4))
    return panel


def _frame(world: World, caption: str, maps: Mapping[str, np.ndarray] | None, words: Sequence[str],
           cell: int) -> np.ndarray:
    grid = _grid_image(world, cell, highlight_target=True)
    panels = [_attention_panel(maps.get(w) if maps else None, w, world, cell) for w in words]
    caption_h = max(14, cell // 2)
    width = grid.width + sum(p.width + PANEL_GAP for p in panels)
    height = caption_h + max([grid.height] + [p.height for p in panels])
    canvas = Image.new("RGB", (width, height), BACKGROUND)
    draw = ImageDraw.Draw(canvas)
    draw.rectangle((0, 0, width, caption_h - 1), fill=CAPTION_BG)
    draw.text((4, 1), caption, fill=TEXT, font=_font(caption_h - 4))
    y0 = caption_h + (height - caption_h - grid.height)
    canvas.paste(grid, (0, y0))
    x = grid.width
    for panel in panels:
        x += PANEL_GAP
        canvas.paste(panel, (x, caption_h))
        x += panel.width
    return np.asarray(canvas)


def render_frames(
    situation: Situation,
    actions: Sequence[Action | str],
    attention: Sequence[Mapping[str, np.ndarray]] | None = None,
    cell_px: int = 40,
) -> list[np.ndarray]:
    """One RGB frame per state: the initial one and one after each action (T+1).

    Actions are executed with `World.step`; a trailing `<eos>` ends the episode
    (shown in the last caption). `attention[t]` (word -> n x n map), if given, is
    the step-t attention that chose action t; it is drawn as one panel per word
    beside frame t, and every frame has a panel for every word seen, so all
    frames have one size (needed for GIFs).
    """
    actions = [a if isinstance(a, Action) else Action.from_token(a) for a in actions]
    if Action.EOS in actions[:-1]:
        raise InvalidActionError("'<eos>' may only be the last action")
    moves = actions[:-1] if actions and actions[-1] is Action.EOS else actions
    attention = list(attention or [])
    words: list[str] = []
    for maps in attention:
        words.extend(w for w in maps if w not in words)
    world = World(situation)
    frames = []
    for t in range(len(moves) + 1):
        if t < len(actions):
            caption = f"t={t}  next: {actions[t].token}"
        else:
            caption = f"t={t}  done"
        maps = attention[t] if t < len(attention) else None
        frames.append(_frame(world, caption, maps, words, cell_px))
        if t < len(moves):
            world.step(moves[t])
    return frames


def save_png(img: np.ndarray, path: str | Path) -> Path:
    path = Path(path)
    Image.fromarray(np.asarray(img, dtype=np.uint8)).save(path, format="PNG")
    return path


def save_gif(frames: Sequence[np.ndarray], path: str | Path, fps: float = 4.0) -> Path:
    """Animated GIF, looping, `fps` frames per second."""
    if not frames:
        raise ValueError("save_gif needs at least one frame")
    path = Path(path)
    images = [Image.fromarray(np.asarray(f, dtype=np.uint8)) for f in frames]
    images[0].save(path, format="GIF", save_all=True, append_images=images[1:],
                   duration=max(20, int(round(1000 / fps))), loop=0)
    return path
