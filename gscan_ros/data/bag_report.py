"""What reading a bag recovered and what it lost (`BagReadReport`), for the reader, the
scanner, `bag repair` and the decode cache (docs/bags.md "Damaged bags")."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path


@dataclass
class BagReadReport:
    """What a read recovered and what it lost.

    `lost_*` compare against metadata.yaml when the writer closed the bag; when it did
    not (killed recorder), they are lower bounds: what was seen to be lost.
    """

    bag_dir: Path
    expected_messages: int | None = None
    expected_episodes: int | None = None
    messages_read: int = 0
    episodes_read: int = 0  # complete episodes, whatever the split filter
    # Episodes that ended other than complete (cut, preempted, rejected), by outcome: no
    # demonstrations, skipped unless asked for; whatever the split filter.
    outcomes: dict[str, int] = field(default_factory=dict)
    incomplete_episodes: int = 0  # started, never properly ended (end of data, damage, a missing message)
    drop_reasons: dict[str, int] = field(default_factory=dict)  # why, for format-2 bags (reason -> episodes)
    discarded_messages: int = 0  # read but outside any complete episode
    truncated_files: list[Path] = field(default_factory=list)  # ended before the MCAP footer
    unread_bytes: int = 0  # trailing bytes that held no complete record
    corrupt_regions: list[tuple[Path, int, int]] = field(default_factory=list)  # damaged bytes [start, end) skipped
    lost_chunks: int = 0  # MCAP chunks that could not be read (damaged, or torn off by a truncation)
    unreadable_messages: int = 0  # messages known to be in lost chunks (MCAP message indexes) or on unknown channels
    finished: bool = False  # every file was read to its end (the counts are final)

    @property
    def truncated(self) -> bool:
        return bool(self.truncated_files)

    @property
    def corrupt(self) -> bool:
        return bool(self.corrupt_regions)

    @property
    def damaged(self) -> bool:
        """A file ended early or held damaged bytes (even when no episode was lost)."""
        return self.truncated or self.corrupt

    @property
    def exact(self) -> bool:
        """The losses are exact (the writer closed the bag), not lower bounds."""
        return self.expected_messages is not None

    @property
    def skipped_bytes(self) -> int:
        return sum(end - start for _, start, end in self.corrupt_regions)

    @property
    def lost_messages(self) -> int:
        """Messages not delivered in a complete episode (a lower bound when the writer died)."""
        kept = self.messages_read - self.discarded_messages
        if self.expected_messages is not None:
            return max(self.expected_messages - kept, 0)
        return self.discarded_messages + self.unreadable_messages

    @property
    def other_outcomes(self) -> int:
        """Episodes that ended other than complete (`outcomes`)."""
        return sum(self.outcomes.values())

    def count_outcome(self, outcome: str) -> None:
        self.outcomes[outcome] = self.outcomes.get(outcome, 0) + 1

    @property
    def lost_episodes(self) -> int:
        if self.expected_episodes is not None:
            return max(self.expected_episodes - self.episodes_read - self.other_outcomes, 0)
        return self.incomplete_episodes

    @property
    def complete(self) -> bool:
        """Nothing lost and nothing damaged."""
        return not (self.damaged or self.lost_episodes or self.lost_messages)

    def state(self) -> str:
        """'intact', 'truncated', 'corrupt' or 'corrupt and truncated'."""
        parts = [word for word, flag in (("corrupt", self.corrupt), ("truncated", self.truncated)) if flag]
        return " and ".join(parts) or "intact"

    def summary(self) -> str:
        """One line: state, what was recovered, what was lost."""
        details = []
        if self.corrupt:
            details.append(
                f"{len(self.corrupt_regions)} damaged region(s), {self.skipped_bytes} bytes skipped"
            )
        if self.lost_chunks:
            details.append(f"{self.lost_chunks} chunk(s) unreadable")
        if self.truncated:
            torn = f": {self.unread_bytes} unreadable trailing bytes" if self.unread_bytes else ""
            details.append(f"no MCAP footer{torn}")
        if self.incomplete_episodes:
            details.append(f"{self.incomplete_episodes} incomplete")
        if self.outcomes:
            details.append(", ".join(f"{n} {outcome}" for outcome, n in sorted(self.outcomes.items()))
                           + " (no demonstrations)")
        of = f" of {self.expected_episodes}" if self.expected_episodes is not None else ""
        bound = "" if self.exact else " at least"
        line = (
            f"{self.bag_dir}: {self.state()}: recovered {self.episodes_read}{of} complete episodes; "
            f"lost{bound} {self.lost_episodes} episodes / {self.lost_messages} messages"
        )
        if not self.exact:
            details.append("the writer did not close the bag")
        return line + (f" ({'; '.join(details)})" if details else "")
