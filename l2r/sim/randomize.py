"""Per-episode randomisation of the runner's body (`RunEnv(randomize=...)`), off by default.

A policy that runs only in the simulator it trained on falls in OpenSim, whose small
differences grow into a fall (docs/model.md): training on bodies that differ a little from
episode to episode asks for a gait that survives them. Each field bounds one kind of draw; each
factor is uniform in [1 - fraction, 1 + fraction], drawn at reset from the env's seeded
generator after the episode's obstacles and psoas strengths, so a seed's course is the same with
or without randomisation. A fraction of 0 draws nothing and changes nothing.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

MUSCLE_FIELDS = ("strength", "tendon_slack", "fiber_length")
CONTACT_FIELDS = ("contact_stiffness", "contact_damping", "friction")


@dataclass(frozen=True)
class Randomization:
    """Fractions of the per-episode draws (0: not drawn)."""

    strength: float = 0.0
    """Each muscle's max isometric force, one factor per muscle."""
    tendon_slack: float = 0.0
    """Each muscle's tendon slack length, one factor per muscle."""
    fiber_length: float = 0.0
    """Each muscle's optimal fibre length, one factor per muscle; the fibre's width and max speed,
    which the .osim derives from it, scale with it."""
    mass: float = 0.0
    """Each body segment's mass, one factor per segment; its inertia scales with it."""
    contact_stiffness: float = 0.0
    """The feet's ground contact stiffness, one factor per episode."""
    contact_damping: float = 0.0
    """The ground contact's dissipation, one factor per episode."""
    friction: float = 0.0
    """The ground's static, dynamic and viscous friction coefficients, one factor for all three."""
    delay: float = 0.0
    """Not a fraction: the probability that an episode's excitations act one physics step
    (0.0025 s) late, the last step's excitations held for that long (1: every episode)."""

    def __post_init__(self):
        for name, value in self.as_dict().items():
            if type(value) not in (int, float) or not math.isfinite(value):
                raise ValueError(f"randomize {name} must be a number, got {value!r}")
            high = 1.0 if name == "delay" else 0.5
            if not 0.0 <= value <= high:
                what = "a probability" if name == "delay" else "a fraction"
                raise ValueError(f"randomize {name} is {what} from 0 to {high}, got {value}")

    def __bool__(self) -> bool:
        return any(self.as_dict().values())

    def as_dict(self) -> dict[str, float]:
        return dataclasses.asdict(self)

    @classmethod
    def of(cls, value: Randomization | Mapping[str, Any] | None) -> Randomization:
        """A Randomization from itself, a mapping of field names to fractions, or None (off);
        ValueError naming an unknown field."""
        if value is None:
            return cls()
        if isinstance(value, Randomization):
            return value
        if not isinstance(value, Mapping):
            raise ValueError(f"randomize takes a mapping of {', '.join(cls.names())} to fractions, got {value!r}")
        unknown = set(value) - set(cls.names())
        if unknown:
            raise ValueError(f"randomize has no {', '.join(sorted(map(str, unknown)))}; "
                             f"it takes {', '.join(cls.names())}")
        return cls(**value)

    @classmethod
    def parse(cls, text: str) -> Randomization:
        """From the command line's form, ``strength=0.05,mass=0.05,delay=0.5`` (empty: off)."""
        values = {}
        for item in filter(None, (part.strip() for part in text.split(","))):
            name, sep, number = item.partition("=")
            try:
                values[name.strip()] = float(number)
            except ValueError:
                sep = ""
            if not sep:
                raise ValueError(f"randomize takes NAME=FRACTION items separated by commas, got {item!r}")
        return cls.of(values)

    def __str__(self) -> str:
        """The command line's form of the factors that are on, as `parse` reads it ('' when off)."""
        return ",".join(f"{name}={value:g}" for name, value in self.as_dict().items() if value)

    @classmethod
    def names(cls) -> tuple[str, ...]:
        return tuple(f.name for f in dataclasses.fields(cls))

    def draw(self, rng: np.random.Generator, muscles: int, segments: int) -> dict[str, Any]:
        """This episode's factors, for the fields that are on: an array per muscle or segment, one
        number per contact property, and ``delay`` a bool."""
        drawn: dict[str, Any] = {}
        for name, count in [(n, muscles) for n in MUSCLE_FIELDS] + [("mass", segments)]:
            fraction = getattr(self, name)
            if fraction:
                drawn[name] = rng.uniform(1.0 - fraction, 1.0 + fraction, count)
        for name in CONTACT_FIELDS:
            fraction = getattr(self, name)
            if fraction:
                drawn[name] = float(rng.uniform(1.0 - fraction, 1.0 + fraction))
        if self.delay:
            drawn["delay"] = bool(rng.random() < self.delay)
        return drawn
