"""The runner's difficulty over an actor's training (`l2r-actor --difficulty-schedule`): flat
ground first, the obstacle course once the policy runs."""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

DIFFICULTIES = (0, 1, 2)
DISTANCE_WINDOW = 20
"""Training episodes whose mean distance a distance stage is judged on."""


@dataclass(frozen=True)
class Reach:
    """A stage's trigger: the actor's last DISTANCE_WINDOW training episodes of the stage before ran
    this far on average (m), whenever that is."""

    distance: float

    def __str__(self) -> str:
        return f"{self.distance:g}m"


@dataclass(frozen=True)
class DifficultySchedule:
    """Stages (trigger, difficulty), entered in order: the first at step 0, each later one when its
    trigger is met, an env step count of the actor's (int, rising over the stages that have one)
    or a distance its episodes reach (`Reach`)."""

    stages: tuple[tuple[int | Reach, int], ...]

    def __post_init__(self):
        if not self.stages or self.stages[0][0] != 0:
            raise ValueError(f"a difficulty schedule starts at step 0, got {self}")
        steps = [trigger for trigger, _ in self.stages if not isinstance(trigger, Reach)]
        if any(b <= a for a, b in zip(steps, steps[1:])):
            raise ValueError(f"a difficulty schedule's steps must rise, got {self}")
        for trigger, difficulty in self.stages:
            if difficulty not in DIFFICULTIES:
                raise ValueError(f"difficulties are 0, 1 or 2, got {difficulty} in {self}")
            if isinstance(trigger, Reach) and not math.isfinite(trigger.distance):
                raise ValueError(f"a stage's distance must be a number of metres, got {trigger} in {self}")

    @classmethod
    def parse(cls, text: str) -> DifficultySchedule:
        """From the command line's form: ``0:0,200000:1,500000:2``, or with a distance, ``0:0,6m:2``."""
        stages = []
        for item in filter(None, (part.strip() for part in text.split(","))):
            trigger, sep, difficulty = (part.strip() for part in item.partition(":"))
            if not (sep and difficulty.isdigit()):
                raise ValueError(f"a difficulty schedule is STEP:DIFFICULTY or DISTANCEm:DIFFICULTY pairs "
                                 f"separated by commas, got {item!r}")
            if trigger.isdigit():
                stages.append((int(trigger), int(difficulty)))
                continue
            try:
                stages.append((Reach(float(trigger.removesuffix("m"))), int(difficulty)))
            except ValueError:
                raise ValueError(f"a stage starts at an env step (200000) or a distance (6m), got {item!r}") from None
            if not trigger.endswith("m"):
                raise ValueError(f"a stage's distance ends with m, got {item!r}")
        return cls(tuple(stages))

    def __str__(self) -> str:
        return ",".join(f"{trigger}:{difficulty}" for trigger, difficulty in self.stages)


class Course:
    """Where a training actor is on its schedule. A stage once entered is kept; the env steps
    count on from `steps_before`, those its place in the run took before this process (a resumed
    run's), while a distance is judged again on this process's own episodes."""

    def __init__(self, schedule: DifficultySchedule, steps_before: int = 0):
        self.schedule, self.steps_before = schedule, steps_before
        self.stage = 0
        self.recent: deque[float] = deque(maxlen=DISTANCE_WINDOW)

    def difficulty(self, steps: int) -> int:
        """The difficulty of an episode starting after `steps` env steps of this process."""
        stages = self.schedule.stages
        while self.stage + 1 < len(stages) and self.reached(stages[self.stage + 1][0], steps):
            self.stage += 1
            self.recent.clear()
        return stages[self.stage][1]

    def reached(self, trigger: int | Reach, steps: int) -> bool:
        if isinstance(trigger, Reach):
            return len(self.recent) == DISTANCE_WINDOW and sum(self.recent) / DISTANCE_WINDOW >= trigger.distance
        return self.steps_before + steps >= trigger

    def record(self, difficulty: int, distance: float) -> None:
        """A training episode of `difficulty` ended, `distance` run: an episode of the stage now."""
        if difficulty == self.schedule.stages[self.stage][1]:
            self.recent.append(distance)
