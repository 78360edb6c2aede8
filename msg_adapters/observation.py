"""Observation uint8[row, col, channel] <-> sensor_msgs/Image "8UC16" (docs/ros.md `observation`).

One pixel per grid cell, its 16 one-hot channels as the pixel's 16 bytes: height =
width = the grid side, step = 16 * width, `header` = when the world reached the state and
the grid frame. Bags written before the observation was an image hold
std_msgs/UInt8MultiArray (dims "row", "col", "channel", MultiArrayLayout strides); those
are still read (`cdr_to_observation` by the bag channel's type, `ObservationDecoder`).
"""
from __future__ import annotations

import struct

import numpy as np

from gscan_ros.interface import EARLIER_OBSERVATION_TYPE, OBSERVATION, OBSERVATION_ENCODING
from gscan_ros.world.types import NUM_CHANNELS, SUPPORTED_GRID_SIZES
from msg_adapters.cdr import PLAIN_ENCAPSULATIONS, cdr_to_msg, msg_to_cdr
from msg_adapters.errors import MessageFormatError
from msg_adapters.header import Header
from msg_adapters.image import image_msg, image_pixels

OBSERVATION_LABELS: tuple[str, ...] = ("row", "col", "channel")  # the earlier UInt8MultiArray layout
# A serialized observation Image starts with the 4-byte CDR encapsulation, then its header
# stamp (int32 sec, uint32 nanosec), then its frame_id (uint32 length, chars, NUL).
_STAMP_END = 12
MAX_LAYOUTS = 16  # layouts a decoder remembers (one per grid size and frame in practice)


def observation_to_cdr(observation: np.ndarray, *, header: Header | None = None) -> bytes:
    """The "8UC16" image of a uint8[row, col, channel] encoding (World.encode())."""
    array = np.asarray(observation)
    if array.dtype != np.uint8 or array.ndim != 3 or array.shape[2] != NUM_CHANNELS:
        raise MessageFormatError(f"observation must be a uint8[row, col, {NUM_CHANNELS}] array, "
                                 f"got {array.dtype}{list(array.shape)}")
    return msg_to_cdr(image_msg(array, OBSERVATION_ENCODING, header))


def cdr_to_observation(data: bytes, msg_type: str = OBSERVATION.type, *,
                       shape: tuple[int, ...] | None = None) -> np.ndarray:
    """uint8[row, col, channel] view of a serialized observation of `msg_type` (a bag's
    `/observation` channel says which); rejects any other layout.

    The grid must be square, a supported size (4-16), with 16 channels; `shape` pins the
    exact sizes instead. The result is a read-only view of the decoded bytes; copy it to
    modify. A UInt8MultiArray is an observation of an earlier bag.
    """
    if msg_type == OBSERVATION.type:
        return _image_observation(cdr_to_msg(data, msg_type), shape)
    if msg_type == EARLIER_OBSERVATION_TYPE:
        return _array_observation(cdr_to_msg(data, msg_type), shape)
    raise MessageFormatError(f"an observation is a {OBSERVATION.type} (or, in earlier bags, a "
                             f"{EARLIER_OBSERVATION_TYPE}), not a {msg_type}")


def _image_observation(msg, shape: tuple[int, ...] | None) -> np.ndarray:
    _check_sizes((msg.height, msg.width, NUM_CHANNELS), shape)
    if msg.step != NUM_CHANNELS * msg.width:
        raise MessageFormatError(f"observation step must be {NUM_CHANNELS} * width = {NUM_CHANNELS * msg.width}, "
                                 f"got {msg.step}")
    return image_pixels(msg, OBSERVATION_ENCODING, NUM_CHANNELS)


class ObservationDecoder:
    """cdr_to_observation for the many observations of one bag channel, fast.

    Observations of one channel differ only in their header stamp (Image), the padding
    bytes that align fields (serializers need not zero them) and their trailing data
    block. The first message of a new layout is decoded in full and checked, and the byte
    spans that fix its layout are found once; a later message of the same length whose
    bytes match those spans is the same message up to the rest, so its tail is its data.
    """

    def __init__(self, msg_type: str = OBSERVATION.type) -> None:
        self.msg_type = msg_type
        self._layout_spans = _image_layout_spans if msg_type == OBSERVATION.type else _array_layout_spans
        self._layouts: list[tuple[int, tuple[slice, ...], list[bytes], int, tuple[int, ...]]] = []

    def __call__(self, data: bytes) -> np.ndarray:
        n = len(data)
        for length, spans, values, size, shape in self._layouts:
            if n == length and [data[span] for span in spans] == values:
                return np.frombuffer(data, np.uint8, count=size, offset=n - size).reshape(shape)
        observation = cdr_to_observation(data, self.msg_type)
        size = observation.size
        spans = self._layout_spans(data, n - size)
        if (spans is not None and len(self._layouts) < MAX_LAYOUTS
                and data[n - size :] == observation.tobytes()):
            self._layouts.append((n, spans, [bytes(data[span]) for span in spans], size, observation.shape))
        return observation


def _image_layout_spans(data: bytes, data_start: int) -> tuple[slice, ...] | None:
    """The spans of a serialized Image that fix its layout: all but the stamp, the padding and
    the pixels (None when the pixels do not start where the fields end, or the CDR is not plain)."""
    endian = PLAIN_ENCAPSULATIONS.get(int.from_bytes(data[:2], "big"))
    if endian is None:
        return None
    (frame_chars,) = struct.unpack_from(f"{endian}I", data, _STAMP_END)
    frame_end = _STAMP_END + 4 + frame_chars
    dims = _aligned(frame_end)  # height, width, then the encoding
    (encoding_chars,) = struct.unpack_from(f"{endian}I", data, dims + 8)
    flag_end = dims + 12 + encoding_chars + 1  # the encoding and is_bigendian
    step = _aligned(flag_end)  # step, then the data length
    if step + 8 != data_start:
        return None
    return slice(0, 4), slice(_STAMP_END, frame_end), slice(dims, flag_end), slice(step, data_start)


def _array_layout_spans(data: bytes, data_start: int) -> tuple[slice, ...]:
    """A serialized UInt8MultiArray observation has no stamp and, its labels being 4 or 8 bytes, no padding."""
    return (slice(0, data_start),)


def _aligned(position: int) -> int:
    """The next 4-byte boundary of the CDR body (which starts after the 4-byte encapsulation)."""
    return position + (-(position - 4)) % 4


def _check_sizes(sizes: tuple[int, ...], shape: tuple[int, ...] | None) -> None:
    if shape is not None and sizes != tuple(shape):
        raise MessageFormatError(f"observation must have sizes {list(shape)}, got {list(sizes)}")
    if shape is None and (sizes[0] != sizes[1] or sizes[0] not in SUPPORTED_GRID_SIZES or sizes[2] != NUM_CHANNELS):
        raise MessageFormatError(f"observation must be a square grid of {SUPPORTED_GRID_SIZES[0]} to "
                                 f"{SUPPORTED_GRID_SIZES[-1]} cells a side with {NUM_CHANNELS} channels, "
                                 f"got sizes {list(sizes)}")


def _strides(shape: tuple[int, ...]) -> tuple[int, ...]:
    """Row-major element strides in the MultiArrayLayout sense (product of inner sizes)."""
    return tuple(int(np.prod(shape[i:])) for i in range(len(shape)))


def _array_observation(msg, shape: tuple[int, ...] | None) -> np.ndarray:
    """The observation of an earlier bag's UInt8MultiArray (dims row, col, channel, row-major)."""
    dims = msg.layout.dim
    labels = tuple(d.label for d in dims)
    if labels != OBSERVATION_LABELS:
        raise MessageFormatError(f"observation layout labels must be {list(OBSERVATION_LABELS)}, got {list(labels)}")
    sizes = tuple(int(d.size) for d in dims)
    _check_sizes(sizes, shape)
    strides = tuple(int(d.stride) for d in dims)
    if strides != _strides(sizes):
        raise MessageFormatError(
            f"observation strides must be row-major {list(_strides(sizes))}, got {list(strides)}"
        )
    if msg.layout.data_offset != 0:
        raise MessageFormatError(f"observation data_offset must be 0, got {msg.layout.data_offset}")
    if msg.data.size != strides[0]:
        raise MessageFormatError(f"observation data has {msg.data.size} bytes, layout needs {strides[0]}")
    return msg.data.reshape(sizes)
