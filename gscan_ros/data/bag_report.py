"""What reading a bag recovered and what it lost (`BagReadReport`), for the reader, the
scanner, `bag repair` and the decode cache (docs/bags.md "Damaged bags")."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from gscan_ros import episode_status as es


@dataclass
class BagReadReport:
    """What a read recovered and what it lost.

    `lost_*` compare against metadata.yaml's counts when the writer closed the bag; else
    (a killed recorder, or no episode count: a `ros2 bag record` bag has none) they are
    lower bounds, what was seen to be lost (`messages_exact`, `episodes_exact`).
    """

    bag_dir: Path
    expected_messages: int | None = None
    expected_episodes: int | None = None
    messages_read: int = 0
    episodes_read: int = 0  # complete episodes, whatever the split filter
    # Episodes that ended other than complete (cut, preempted, rejected), by outcome: no
    # demonstrations, skipped unless asked for; whatever the split filter.
    outcomes: dict[str, int] = field(default_factory=dict)
    refused_commands: int = 0  # of `outcomes`' rejected: commands refused before any episode began
    taken_outcomes: dict[str, int] = field(default_factory=dict)  # of `outcomes`: those handed out (include_incomplete)
    incomplete_episodes: int = 0  # started, never properly ended (end of data, damage, a missing message)
    drop_reasons: dict[str, int] = field(default_factory=dict)  # why, where known (reason -> episodes)
    bad_messages: int = 0  # stack messages that could not be read (each lost; its episode dropped)
    first_bad_message: str | None = None  # the first of them: topic, publish time, why
    grid_sizes: dict[int, int] = field(default_factory=dict)  # grid size -> episodes read (the selected ones)
    discarded_messages: int = 0  # read but outside any complete episode
    duplicate_messages: int = 0  # read twice (same topic, publish time and bytes): the copy is dropped, not lost
    missing_topics: list[str] = field(default_factory=list)  # no stack in the bag: the episode topics it lacks
    late_messages: int = 0  # logged beyond the reorder window from their publication order: each lost
    truncated_files: list[Path] = field(default_factory=list)  # ended before the MCAP footer
    missing_files: list[Path] = field(default_factory=list)  # storage files of the bag that are absent (all lost)
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
    def missing(self) -> bool:
        return bool(self.missing_files)

    @property
    def damaged(self) -> bool:
        """A file ended early, held damaged bytes or is missing (even when no episode was lost)."""
        return self.truncated or self.corrupt or self.missing

    @property
    def messages_exact(self) -> bool:
        """`lost_messages` is exact (the writer closed the bag), not a lower bound."""
        return self.expected_messages is not None

    @property
    def episodes_exact(self) -> bool:
        """`lost_episodes` is exact (our writer closed the bag and counted its episodes)."""
        return self.expected_episodes is not None

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

    def count_outcome(self, outcome: str, *, taken: bool = False) -> None:
        """One more episode that ended `outcome` (not complete); `taken`: handed to the caller."""
        self.outcomes[outcome] = self.outcomes.get(outcome, 0) + 1
        if taken:
            self.taken_outcomes[outcome] = self.taken_outcomes.get(outcome, 0) + 1

    def count_refused(self) -> None:
        """A command refused before any episode began: a rejected outcome with no episode."""
        self.count_outcome(es.REJECTED)
        self.refused_commands += 1

    def count_drop(self, reason: str | None, episodes: int = 1) -> None:
        """`episodes` more episodes that could not be read back, for `reason` when known."""
        self.incomplete_episodes += episodes
        if reason is not None:
            self.drop_reasons[reason] = self.drop_reasons.get(reason, 0) + episodes

    def count_late(self, message=None) -> None:
        """A message logged too far from its publication order to be put back: lost, with the
        episode it fell into (`publication_order`)."""
        self.late_messages += 1

    def count_duplicate(self, message=None) -> None:
        """A message the bag holds twice; its copy is left out (`without_duplicates`)."""
        self.duplicate_messages += 1

    def count_grid_size(self, grid_size: int) -> None:
        self.grid_sizes[grid_size] = self.grid_sizes.get(grid_size, 0) + 1

    def mixed_grid_sizes(self) -> str | None:
        """One line when the episodes read lie on more than one grid size (None: one or none).
        A model takes one grid size, and training stacks every state of a bag into one array."""
        if len(self.grid_sizes) < 2:
            return None
        sizes = ", ".join(f"{n} on {g}x{g}" for g, n in sorted(self.grid_sizes.items()))
        return f"{self.bag_dir}: episodes on {len(self.grid_sizes)} grid sizes ({sizes}); a dataset has one"

    @property
    def lost_episodes(self) -> int:
        if self.expected_episodes is not None:
            return max(self.expected_episodes - self.episodes_read - self.other_outcomes, 0)
        return self.incomplete_episodes

    @property
    def complete(self) -> bool:
        """Nothing lost and nothing damaged."""
        return not (self.damaged or self.lost_episodes or self.lost_messages or self.late_messages)

    def state(self) -> str:
        """'intact', or what is wrong: 'corrupt', 'truncated', 'missing files', joined by 'and'."""
        parts = [word for word, flag in (("corrupt", self.corrupt), ("truncated", self.truncated),
                                         ("missing files", self.missing)) if flag]
        return " and ".join(parts) or "intact"

    def summary(self) -> str:
        """One line: state, what was recovered, what was lost."""
        details = []
        if self.missing_topics:
            details.append(f"no gSCAN stack: it lacks {', '.join(self.missing_topics)}, which episodes are read from")
        if self.missing:
            names = ", ".join(p.name for p in self.missing_files[:3]) + (", ..." if len(self.missing_files) > 3 else "")
            details.append(f"{len(self.missing_files)} storage file(s) missing: {names}")
        if self.corrupt:
            details.append(
                f"{len(self.corrupt_regions)} damaged region(s), {self.skipped_bytes} bytes skipped"
            )
        if self.lost_chunks:
            details.append(f"{self.lost_chunks} chunk(s) unreadable")
        if self.truncated:
            torn = f": {self.unread_bytes} unreadable trailing bytes" if self.unread_bytes else ""
            details.append(f"no MCAP footer{torn}")
        if self.bad_messages:
            details.append(f"{self.bad_messages} bad message(s), the first {self.first_bad_message}")
        if self.late_messages:
            details.append(f"{self.late_messages} message(s) logged beyond the reorder window from their "
                           f"publication order, each lost with the episode it fell into")
        if self.duplicate_messages:
            details.append(f"{self.duplicate_messages} duplicate message(s) left out")
        if self.incomplete_episodes:
            reasons = self.reasons()
            details.append(f"{self.incomplete_episodes} incomplete" + (f": {reasons}" if reasons else ""))
        if self.outcomes:
            details.append(", ".join(f"{n} {outcome}" for outcome, n in sorted(self.outcomes.items()))
                           + " (no demonstrations)")
        if not (self.messages_exact and self.episodes_exact):
            details.append("the writer did not close the bag" if not self.messages_exact
                           else "the bag does not say how many episodes it holds")
        # The bag's count holds every outcome; only the complete episodes are recovered as demonstrations.
        of = f" (of {self.expected_episodes} recorded)" if self.episodes_exact else ""
        line = (
            f"{self.bag_dir}: {self.state()}: recovered {self.episodes_read} complete episodes{of}; "
            f"lost {self.bound(self.episodes_exact)}{self.lost_episodes} episodes / "
            f"{self.bound(self.messages_exact)}{self.lost_messages} messages"
        )
        return line + (f" ({'; '.join(details)})" if details else "")

    def reasons(self) -> str:
        """Why episodes were dropped: 'cut by lost data (2), a bad /action message (1)'."""
        return ", ".join(f"{reason} ({n})" for reason, n in sorted(self.drop_reasons.items()))

    @staticmethod
    def bound(exact: bool) -> str:
        """'' before an exact count, 'at least ' before a lower bound."""
        return "" if exact else "at least "


def incomplete_line(readers, verb: str, *, included: bool) -> str | None:
    """One line on the recorded episodes of `readers` (BagEpisodeReaders) that did not end
    complete, by outcome, and which of them a command `verb` (`included`: it asked for
    them). A command refused before any episode began is counted but is no episode to take;
    the others left are outside the selection (--splits, a limit). None when there are none."""
    total: dict[str, int] = {}
    took: dict[str, int] = {}
    refused = 0
    for reader in readers:
        for outcome, n in reader.report.outcomes.items():
            total[outcome] = total.get(outcome, 0) + n
        for outcome, n in reader.report.taken_outcomes.items():
            took[outcome] = took.get(outcome, 0) + n
        refused += reader.report.refused_commands
    if not total:
        return None
    line = "episodes that did not end complete: " + _by_outcome(total)
    if not included:
        return f"{line} (not {verb})"
    left = sum(total.values()) - sum(took.values()) - refused
    details = [f"{verb}: {_by_outcome(took) or 'none'}"]
    if refused:
        details.append(f"{refused} refused before any action, nothing to take")
    if left:
        details.append(f"{left} outside the selection")
    return f"{line} ({'; '.join(details)})"


def _by_outcome(counts: dict[str, int]) -> str:
    return ", ".join(f"{n} {outcome}" for outcome, n in sorted(counts.items()))

