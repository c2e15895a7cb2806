"""The runner's difficulty over an actor's training (`l2r-actor --difficulty-schedule`): flat
ground first, the obstacle course once the policy runs."""

from __future__ import annotations

import bisect
from dataclasses import dataclass

DIFFICULTIES = (0, 1, 2)


@dataclass(frozen=True)
class DifficultySchedule:
    """Stages (first env step, difficulty), from step 0 on and in rising steps: an episode starts
    at the difficulty of the last stage whose first step the actor's env steps have reached."""

    stages: tuple[tuple[int, int], ...]

    def __post_init__(self):
        if not self.stages or self.stages[0][0] != 0:
            raise ValueError(f"a difficulty schedule starts at step 0, got {self}")
        steps = [step for step, _ in self.stages]
        if any(b <= a for a, b in zip(steps, steps[1:])):
            raise ValueError(f"a difficulty schedule's steps must rise, got {self}")
        for _, difficulty in self.stages:
            if difficulty not in DIFFICULTIES:
                raise ValueError(f"difficulties are 0, 1 or 2, got {difficulty} in {self}")

    @classmethod
    def parse(cls, text: str) -> DifficultySchedule:
        """From the command line's form: ``0:0,200000:1,500000:2``."""
        stages = []
        for item in filter(None, (part.strip() for part in text.split(","))):
            step, sep, difficulty = item.partition(":")
            if not (sep and step.strip().isdigit() and difficulty.strip().isdigit()):
                raise ValueError(f"a difficulty schedule is STEP:DIFFICULTY pairs separated by commas, got {item!r}")
            stages.append((int(step), int(difficulty)))
        return cls(tuple(stages))

    def at(self, steps: int) -> int:
        """The difficulty of an episode starting after `steps` env steps."""
        return self.stages[bisect.bisect_right([step for step, _ in self.stages], steps) - 1][1]

    def __str__(self) -> str:
        return ",".join(f"{step}:{difficulty}" for step, difficulty in self.stages)
