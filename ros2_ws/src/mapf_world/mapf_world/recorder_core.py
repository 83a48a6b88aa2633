"""Loss accounting of the recorder (no rclpy needed here).

A DDS writer numbers its samples 1, 2, 3, ... (rmw message info `publication_sequence_number`).
On a topic with one publisher, a jump in the numbers the recorder receives is a message it never
got; a number that does not grow means another writer (the publisher was restarted). Topics with
several publishers at once (/rosout) interleave several numberings and are not accounted.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional


@dataclass
class TopicSequence:
    received: int = 0      # messages the recorder got
    published: int = 0     # messages the writers numbered, from the first one the recorder got of each writer
    writers: int = 0       # numberings seen (1 + publisher restarts)
    last: Optional[int] = None

    @property
    def lost(self) -> int:
        return self.published - self.received


class SequenceTracker:
    """Counts, per single-publisher topic, the messages published and the messages received."""

    def __init__(self):
        self.topics: Dict[str, TopicSequence] = {}

    def track(self, topic: str) -> None:
        self.topics.setdefault(topic, TopicSequence())

    def untrack(self, topic: str) -> None:
        """Stop accounting a topic that has gained a second publisher (its numberings would interleave)."""
        self.topics.pop(topic, None)

    def received(self, topic: str, sequence: Optional[int]) -> None:
        t = self.topics.get(topic)
        if t is None or sequence is None:  # not accounted, or the middleware does not number samples
            return
        t.received += 1
        if t.last is None or sequence <= t.last:  # the first message, or a new writer
            t.writers += 1
            t.published += 1
        else:
            t.published += sequence - t.last
        t.last = sequence

    @property
    def published(self) -> int:
        return sum(t.published for t in self.topics.values())

    @property
    def lost(self) -> int:
        return sum(t.lost for t in self.topics.values())

    def report(self) -> str:
        worst = sorted(((t.lost, name) for name, t in self.topics.items() if t.lost), reverse=True)[:5]
        text = (f"{self.published} published, {self.published - self.lost} received, {self.lost} lost "
                f"on {len(self.topics)} single-publisher topics")
        return text + ("" if not worst else " (most on " + ", ".join(f"{n} {k}" for k, n in worst) + ")")
