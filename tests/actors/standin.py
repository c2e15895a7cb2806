"""A tiny stand-in with the runner's shapes (41 observations, 18 excitations), for fast tests."""

import gymnasium
import numpy as np


class StandIn(gymnasium.Env):
    def __init__(self, difficulty: int = 0, seed: int | None = None, length: int = 40):
        self.observation_space = gymnasium.spaces.Box(-np.inf, np.inf, (41,), np.float32)
        self.action_space = gymnasium.spaces.Box(0.0, 1.0, (18,), np.float32)
        self.length = length
        self._x = 0.0
        self._t = 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self._x, self._t = 0.0, 0
        return self.np_random.normal(size=41).astype(np.float32), {"distance": 0.0}

    def step(self, action):
        action = np.asarray(action)
        assert action.shape == (18,) and np.isfinite(action).all()
        self._t += 1
        reward = float(action.mean() - 0.5) * 0.01
        self._x += reward
        obs = self.np_random.normal(size=41).astype(np.float32)
        return obs, reward, False, self._t >= self.length, {"distance": self._x}


gymnasium.register("StandIn-v0", entry_point=StandIn)


class Broken(StandIn):
    """A stand-in that breaks its own declared space after 5 steps: 40 observations, not 41."""

    def step(self, action):
        obs, *rest = super().step(action)
        return (obs[:40] if self._t > 5 else obs, *rest)


gymnasium.register("BrokenStandIn-v0", entry_point=Broken)


class Counting(StandIn):
    """A stand-in whose observation is a count, a Discrete space: no observation l2r takes."""

    def __init__(self, difficulty: int = 0, seed: int | None = None):
        super().__init__(difficulty, seed)
        self.observation_space = gymnasium.spaces.Discrete(40)


gymnasium.register("CountingStandIn-v0", entry_point=Counting)


class Faller(StandIn):
    """A stand-in whose episodes also end by a fall (terminated), at steps its seed draws: about
    one step in 15."""

    def step(self, action):
        obs, reward, _, truncated, info = super().step(action)
        return obs, reward, bool(obs[0] > 1.5), truncated, info


gymnasium.register("Faller-v0", entry_point=Faller)


class InstantWorlds(gymnasium.vector.VectorEnv):
    """Worlds with `l2r/RunWarp-v0`'s shapes and info entries and no physics, reset only when
    asked (autoreset DISABLED): what an actor's own loop costs per world (bench/actor_step.py)."""

    metadata = {"autoreset_mode": gymnasium.vector.AutoresetMode.DISABLED}

    def __init__(self, num_envs: int = 1, **kwargs):
        self.num_envs = num_envs
        self.single_observation_space = gymnasium.spaces.Box(-np.inf, np.inf, (41,), np.float32)
        self.single_action_space = gymnasium.spaces.Box(0.0, 1.0, (18,), np.float32)
        self.observation_space = gymnasium.vector.utils.batch_space(self.single_observation_space, num_envs)
        self.action_space = gymnasium.vector.utils.batch_space(self.single_action_space, num_envs)
        self._t = np.zeros(num_envs, np.int64)
        self._rng = np.random.default_rng(0)

    def _info(self) -> dict:
        n = self.num_envs
        shapes = {"body_pos": (14, 3), "body_quat": (14, 4), "muscle_activation": (18,), "muscle_length": (18,),
                  "muscle_force": (18,), "fiber_length": (18,), "ligament_force": (8,), "contact_force": (4, 3)}
        return {"distance": self._t * 0.01, **{name: np.zeros((n, *shape)) for name, shape in shapes.items()},
                "diverged": np.zeros(n, bool)}

    def reset(self, *, seed=None, options=None):
        mask = (options or {}).get("reset_mask")
        self._t[slice(None) if mask is None else mask] = 0
        return self._rng.random((self.num_envs, 41), dtype=np.float32), self._info()

    def step(self, actions):
        self._t += 1
        fell = self._rng.random(self.num_envs) < 0.01  # episodes of about 100 steps
        return (self._rng.random((self.num_envs, 41), dtype=np.float32), np.full(self.num_envs, 0.01), fell,
                self._t >= 1000, self._info())


gymnasium.register("InstantWorlds-v0", vector_entry_point=InstantWorlds)


class Diverging(StandIn):
    """A stand-in whose physics blows up at its 7th step: a NaN observation that ends the episode
    (as `l2r/RunWarp-v0` ends a world whose state turns non-finite)."""

    def step(self, action):
        obs, reward, terminated, truncated, info = super().step(action)
        if self._t == 7:
            return np.full_like(obs, np.nan), 0.0, True, truncated, info
        return obs, reward, terminated, truncated, info


gymnasium.register("Diverging-v0", entry_point=Diverging)
