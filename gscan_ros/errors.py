"""One exception family for the whole project.

Every error a user can cause (bad action, malformed dataset, unknown word, bad
checkpoint) derives from `GscanError`, so CLIs and nodes can report it as one line
without a traceback, and tests can assert the documented type.
"""


class GscanError(Exception):
    """Base class of every user-facing error of gscan_ros."""


class InvalidActionError(GscanError):
    """An action that is unknown or cannot be executed in the current world state."""


class SituationError(GscanError):
    """A situation (or its gSCAN JSON) that is malformed or inconsistent."""


class DatasetFormatError(GscanError):
    """A dataset.txt / bag whose content does not follow the gSCAN format."""


class CommandError(GscanError):
    """A command that cannot be tokenized or parsed (unknown word, empty, too long ...)."""


class GraphError(GscanError):
    """A CommandGraph (or its JSON) that violates the graph invariants."""


class CheckpointError(GscanError):
    """A checkpoint that cannot be loaded or does not match the config/vocabulary."""


class LexiconError(GscanError):
    """WordNet data missing or unusable."""
