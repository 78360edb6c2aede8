"""Observation uint8[row, col, channel] <-> std_msgs/UInt8MultiArray (docs/ros.md `observation`).

The layout follows the std_msgs/MultiArrayLayout convention: one dimension per array
axis, outermost first, `stride` = number of elements spanned by one step of the axis
(so `dim[0].stride` is the total size) and `data_offset` 0. Labels are fixed
("row", "col", "channel") so a subscriber can check it is reading an observation and
not some other byte array.
"""
from __future__ import annotations

import numpy as np
from std_msgs.msg import MultiArrayDimension, UInt8MultiArray

from gscan_ros.world.types import NUM_CHANNELS, SUPPORTED_GRID_SIZES
from msg_adapters.cdr import cdr_to_msg
from msg_adapters.errors import MessageFormatError

OBSERVATION_LABELS: tuple[str, ...] = ("row", "col", "channel")


def _strides(shape: tuple[int, ...]) -> tuple[int, ...]:
    """Row-major element strides in the MultiArrayLayout sense (product of inner sizes)."""
    return tuple(int(np.prod(shape[i:])) for i in range(len(shape)))


def observation_to_msg(observation: np.ndarray) -> UInt8MultiArray:
    """Wrap a uint8[row, col, channel] encoding (World.encode()) in a UInt8MultiArray."""
    array = np.asarray(observation)
    if array.dtype != np.uint8 or array.ndim != 3:
        raise MessageFormatError(
            f"observation must be a uint8[row, col, channel] array, got {array.dtype}{list(array.shape)}"
        )
    msg = UInt8MultiArray()
    msg.layout.dim = [
        MultiArrayDimension(label=label, size=size, stride=stride)
        for label, size, stride in zip(OBSERVATION_LABELS, array.shape, _strides(array.shape))
    ]
    msg.layout.data_offset = 0
    msg.data = np.ascontiguousarray(array).tobytes()
    return msg


def msg_to_observation(msg: UInt8MultiArray, *, shape: tuple[int, ...] | None = None) -> np.ndarray:
    """uint8[row, col, channel] view of the message data; rejects any other layout.

    The grid comes from the layout: square, a supported size (4-16), 16 channels;
    `shape` pins the exact sizes instead. The result is read-only (it shares the
    message's buffer); copy it to modify.
    """
    dims = msg.layout.dim
    labels = tuple(d.label for d in dims)
    if labels != OBSERVATION_LABELS:
        raise MessageFormatError(f"observation layout labels must be {list(OBSERVATION_LABELS)}, got {list(labels)}")
    sizes = tuple(int(d.size) for d in dims)
    if shape is not None and sizes != tuple(shape):
        raise MessageFormatError(f"observation must have sizes {list(shape)}, got {list(sizes)}")
    if shape is None and (sizes[0] != sizes[1] or sizes[0] not in SUPPORTED_GRID_SIZES or sizes[2] != NUM_CHANNELS):
        raise MessageFormatError(f"observation must be a square grid of {SUPPORTED_GRID_SIZES[0]} to "
                                 f"{SUPPORTED_GRID_SIZES[-1]} cells a side with {NUM_CHANNELS} channels, "
                                 f"got sizes {list(sizes)}")
    strides = tuple(int(d.stride) for d in dims)
    if strides != _strides(sizes):
        raise MessageFormatError(
            f"observation strides must be row-major {list(_strides(sizes))}, got {list(strides)}"
        )
    if msg.layout.data_offset != 0:
        raise MessageFormatError(f"observation data_offset must be 0, got {msg.layout.data_offset}")
    data = np.frombuffer(msg.data, dtype=np.uint8)
    if data.size != strides[0]:
        raise MessageFormatError(f"observation data has {data.size} bytes, layout needs {strides[0]}")
    return data.reshape(sizes)


def cdr_to_observation(data: bytes, *, shape: tuple[int, ...] | None = None) -> np.ndarray:
    """msg_to_observation of a serialized UInt8MultiArray (a bag's `/observation` record)."""
    return msg_to_observation(cdr_to_msg(data, UInt8MultiArray), shape=shape)
