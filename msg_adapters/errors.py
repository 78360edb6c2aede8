"""The one error a message adapter raises for a message it cannot convert."""
from gscan_ros.errors import GscanError


class MessageFormatError(GscanError, ValueError):
    """A ROS message (or array) whose layout, encoding or shape does not match the adapter.

    Also a `ValueError`, because a wrong array handed to `*_to_cdr` is a caller bug of
    the same kind as NumPy's shape errors.
    """
