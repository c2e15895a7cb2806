"""l2r: distributed actor/learner reinforcement learning over Eclipse Zenoh."""

import importlib.metadata

__version__ = importlib.metadata.version("l2r")
