"""Images <-> sensor_msgs/Image: the rendered world (rgb8) and attention maps (mono8).

Attention maps are published for viewers (rqt, Foxglove), so they are scaled to the
full 0-255 range (divided by their maximum: the image shows *where* a word module
looks, not the absolute mass) and upsampled by an integer factor so one grid cell is
a visible block of pixels. The inverse recovers that normalized 6x6 map.
"""
from __future__ import annotations

import numpy as np

from gscan_ros.world.types import GRID_SIZE
from msg_adapters.cdr import cdr_to_msg, message_class, msg_to_cdr
from msg_adapters.errors import MessageFormatError
from msg_adapters.header import Header, make_header

Image = message_class("sensor_msgs/msg/Image")
RGB8 = "rgb8"
MONO8 = "mono8"
DEFAULT_ATTENTION_UPSAMPLE = 10


def image_msg(pixels: np.ndarray, encoding: str, header: Header | None) -> Image:
    """sensor_msgs/Image of uint8[H, W] or uint8[H, W, channels] pixels, rows unpadded."""
    height, width = pixels.shape[:2]
    channels = 1 if pixels.ndim == 2 else pixels.shape[2]
    return Image(
        header=header if header is not None else make_header(),
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=0,
        step=width * channels,
        data=np.ascontiguousarray(pixels).reshape(-1),
    )


def image_pixels(msg: Image, encoding: str, channels: int) -> np.ndarray:
    """uint8[H, W, channels] view of an image message of `encoding`, dropping any row padding."""
    if msg.encoding != encoding:
        raise MessageFormatError(f"image encoding must be {encoding!r}, got {msg.encoding!r}")
    row_bytes = msg.width * channels
    if msg.step < row_bytes:
        raise MessageFormatError(f"image step {msg.step} is shorter than a {msg.width}-pixel {encoding} row")
    data = msg.data
    if data.size != msg.height * msg.step:
        raise MessageFormatError(
            f"image data has {data.size} bytes, {msg.height} rows of step {msg.step} need {msg.height * msg.step}"
        )
    rows = data.reshape(msg.height, msg.step)[:, :row_bytes]
    return rows.reshape(msg.height, msg.width, channels)


def image_to_cdr(rgb: np.ndarray, *, header: Header | None = None) -> bytes:
    """sensor_msgs/Image (rgb8) of a uint8[H, W, 3] picture such as World.render()."""
    pixels = np.asarray(rgb)
    if pixels.dtype != np.uint8 or pixels.ndim != 3 or pixels.shape[2] != 3:
        raise MessageFormatError(f"image must be a uint8[H, W, 3] RGB array, got {pixels.dtype}{list(pixels.shape)}")
    return msg_to_cdr(image_msg(pixels, RGB8, header))


def cdr_to_image(data: bytes) -> np.ndarray:
    """uint8[H, W, 3] picture of a serialized rgb8 image (read-only view)."""
    return image_pixels(cdr_to_msg(data, Image.__msgtype__), RGB8, 3)


def image_header(data: bytes) -> Header:
    """The header of a serialized sensor_msgs/Image: when and where its picture was taken."""
    return cdr_to_msg(data, Image.__msgtype__).header


def attention_to_cdr(
    attention: np.ndarray, *, upsample: int = DEFAULT_ATTENTION_UPSAMPLE, header: Header | None = None
) -> bytes:
    """mono8 image of a non-negative attention map, max -> 255, each cell `upsample`^2 pixels."""
    weights = np.asarray(attention, dtype=np.float64)
    if weights.ndim != 2:
        raise MessageFormatError(f"attention map must be 2-D [row, col], got shape {list(weights.shape)}")
    if not np.all(np.isfinite(weights)) or np.any(weights < 0):
        raise MessageFormatError("attention map must hold finite non-negative weights")
    if not isinstance(upsample, (int, np.integer)) or upsample < 1:
        raise MessageFormatError(f"attention upsample factor must be a positive integer, got {upsample!r}")
    peak = weights.max(initial=0.0)
    scaled = weights / peak if peak > 0 else weights
    pixels = np.rint(scaled * 255).astype(np.uint8)
    pixels = np.repeat(np.repeat(pixels, upsample, axis=0), upsample, axis=1)
    return msg_to_cdr(image_msg(pixels, MONO8, header))


def cdr_to_attention(data: bytes, *, grid_size: int = GRID_SIZE) -> np.ndarray:
    """float32[grid, grid] in [0, 1] (max-normalized) from a serialized mono8 attention image
    of a `grid_size` world (the 6x6 compositional grid by default)."""
    msg = cdr_to_msg(data, Image.__msgtype__)
    pixels = image_pixels(msg, MONO8, 1)[:, :, 0]
    if msg.height != msg.width or msg.height % grid_size:
        raise MessageFormatError(
            f"attention image must be square with a side divisible by {grid_size}, got {msg.height}x{msg.width}"
        )
    factor = msg.height // grid_size
    blocks = pixels.reshape(grid_size, factor, grid_size, factor).astype(np.float32)
    return blocks.mean(axis=(1, 3)) / np.float32(255)
