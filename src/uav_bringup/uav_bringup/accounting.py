"""What a recorder got of each topic, counted exactly from the publishers' own sequence numbers (no ROS).

Every message carries its publisher's publication sequence number (1, 2, 3, ... per publisher; rmw's message info).
A message that never reached the recorder - overwritten in a full reader queue while the writer was behind, dropped
by a best-effort publisher, overwritten in the publisher's own queue before it was delivered - leaves a gap in its
publisher's numbers: the gap is the exact count lost. What a publisher sent before its first message that reached
the recorder is counted apart (`before`): sent before the recorder matched it (not for the bag), or lost before
anything of it came (a stream that opens with a flood); the numbers cannot tell those apart. A launcher that wants a
whole flight starts it once the recorder has heard each publisher (`fly` does: RecorderReports.wait_for_policy).

rclpy gives no publisher identity with a message, so each topic's messages are told apart into publisher streams by
their numbers: a message continues the stream it follows by one, else the one it follows most closely (a gap), else it
begins a new stream (a publisher that joined or restarted). With one publisher a topic's counts are exact; with several
(/diagnostics) a stream can be mistaken for another only when their numbers come within a gap of each other.
"""

from __future__ import annotations

import dataclasses

from uav_common import contract


@dataclasses.dataclass
class TopicCount:
    written: int = 0  # messages received and written
    lost: int = 0  # gaps in a publisher's numbers: messages it published that never reached the recorder
    before: int = 0  # messages a publisher had published before its first one reached the recorder
    streams: list[int] = dataclasses.field(default_factory=list)  # the newest number of each publisher stream

    def add(self, seq: int | None) -> int:
        """One message received (`seq`: its publication sequence number, None where the middleware gives none);
        the number of messages found lost before it."""
        self.written += 1
        if seq is None or seq <= 0:
            return 0
        if seq - 1 in self.streams:
            self.streams[self.streams.index(seq - 1)] = seq
            return 0
        below = [i for i, last in enumerate(self.streams) if last < seq]
        if below:
            i = max(below, key=lambda i: self.streams[i])
            gap = seq - self.streams[i] - 1
            self.streams[i] = seq
            self.lost += gap
            return gap
        self.streams.append(seq)  # a new publisher (or one that restarted): what it sent before was not for us
        self.before += seq - 1
        return 0


class Accounting:
    """Per-topic counts: `add(topic, seq)` for every message received; `lost` {topic: n} where any were."""

    def __init__(self):
        self.topics: dict[str, TopicCount] = {}

    def track(self, topic: str) -> None:
        """Count `topic` from now on (written 0 until its first message)."""
        self.topics.setdefault(topic, TopicCount())

    def add(self, topic: str, seq: int | None) -> int:
        return self.topics.setdefault(topic, TopicCount()).add(seq)

    @property
    def written(self) -> dict[str, int]:
        """{topic: messages written} of every topic tracked."""
        return {t: c.written for t, c in self.topics.items()}

    @property
    def lost(self) -> dict[str, int]:
        return {t: c.lost for t, c in self.topics.items() if c.lost}

    @property
    def before(self) -> dict[str, int]:
        """{topic: messages its publishers sent before their first one reached the recorder}, where any were."""
        return {t: c.before for t, c in self.topics.items() if c.before}

    def metadata(self) -> dict[str, str]:
        """For the bag's metadata (custom_data): per topic written, lost and before-recording counts."""
        out = {}
        for t, c in self.topics.items():
            out[f"written {t}"] = str(c.written)
            out[f"{contract.LOST_KEY}{t}"] = str(c.lost)
            out[f"before_recording {t}"] = str(c.before)
        return out
