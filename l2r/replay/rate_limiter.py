"""When a learner may sample: Reverb's minimum size and samples-per-insert limiter.

Sampling waits until ``min_size`` transitions are stored. With ``samples_per_insert`` set,
a learner may then have sampled at most ``samples_per_insert * (inserted - min_size) +
error_buffer`` transitions in total, so a fast learner waits for new data instead of
overfitting the old. Inserts are not blocked unless ``hold_inserts`` asks for it: then, while the
actors are more than twice ``error_buffer`` sampled transitions ahead, the shard asks
them to wait (``ReplayAck.hold``), as Reverb blocks inserts, so that the ratio holds both ways
(one gradient step per env step, as Stable-Baselines3 trains, however slow the learner).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class RateLimiter:
    min_size: int = 1000
    """Transitions stored before any sampling."""
    samples_per_insert: float = 0.0
    """Sampled transitions allowed per inserted transition; 0 turns the ratio limit off."""
    error_buffer: float = 10_000.0
    """Slack around the ratio, in sampled transitions."""
    hold_inserts: bool = False
    """Ask actors to wait while they are more than twice ``error_buffer`` ahead of the ratio."""
    inserted: int = 0
    sampled: int = 0

    def can_sample(self, size: int, batch_size: int) -> tuple[bool, str]:
        """Whether a batch may be sampled now, and why not."""
        if size < self.min_size or size == 0:
            return False, f"replay holds {size} transitions, sampling starts at {self.min_size}"
        if self.samples_per_insert > 0 and self.sampled + batch_size > self.allowance():
            return False, (f"samples per insert {self.samples_per_insert}: {self.sampled} sampled, "
                           f"{self.inserted} inserted; waiting for data")
        return True, ""

    def inserts_ahead(self) -> bool:
        """Whether the actors are more than twice ``error_buffer`` ahead of the ratio (a ratio set)."""
        return self.samples_per_insert > 0 and self.allowance() - self.sampled > 2 * self.error_buffer

    def allowance(self) -> float:
        return self.samples_per_insert * (self.inserted - self.min_size) + self.error_buffer

    def retry_after(self, batch_size: int, inserts_per_s: float) -> float:
        """A good delay before asking again, from the current insert rate (bounded to [5 ms, 0.5 s])."""
        if self.samples_per_insert <= 0 or inserts_per_s <= 0:
            return 0.05
        missing = (self.sampled + batch_size - self.allowance()) / self.samples_per_insert
        return min(0.5, max(0.005, missing / inserts_per_s))
