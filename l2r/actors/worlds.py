"""The environments an actor steps, behind one small interface: `Worlds`.

`EnvList` is a list of single gymnasium envs stepped one after another; `VectorWorlds` is a
gymnasium VectorEnv whose N worlds one `step(actions)` call advances (`l2r/RunWarp-v0` on a Warp
device). The actor sees the same per-world steps from both: each world's observation, reward,
terminated, truncated and info, the observation of a world whose episode ended being that
episode's last; `reset_worlds` then gives the first observations of the finished worlds' next
episodes, all in one call.

What `VectorWorlds` needs of a vector env (`metadata["autoreset_mode"]`):
- `AutoresetMode.DISABLED`: worlds are reset only when asked, by gymnasium's masked reset,
  `reset(seed=[one per world], options={"reset_mask": mask, ...})`. The actor resets the
  finished worlds, each with its own episode seed, and the options (the difficulty), as it resets
  single envs (`l2r/RunWarp-v0` under an actor).
  With an action repeated, such an env must take steps of a world whose episode has ended (the
  actor discards them); gymnasium's SyncVectorEnv does not, so its envs repeat actions themselves.
- `AutoresetMode.SAME_STEP` (`l2r/RunWarp-v0` as gymnasium makes it): the step that ends an
  episode begins the next one; its info holds the last state in `final_obs` and `final_info`
  (masked by `_final_obs`) and the new episode's first state in its other entries. The env draws
  its episodes itself from the seed of its first reset: the actor's per-episode seeds and
  options do not reach it.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Protocol

import gymnasium
import numpy as np
from gymnasium.vector import AutoresetMode

Step = tuple[Any, float, bool, bool, dict]  # one world's observation, reward, terminated, truncated, info


class Worlds(Protocol):
    """The worlds one actor steps in lock-step."""

    action_space: gymnasium.Space  # one world's
    observation_space: gymnasium.Space  # one world's

    def reset(self, seeds: list[int], options: dict | None) -> list[tuple[Any, dict]]:
        """Start every world's first episode, world i's from seeds[i]; each world's (observation, info)."""

    def step(self, actions: np.ndarray) -> list[Step]:
        """Advance every world by one action (a row of ``actions`` each)."""

    def reset_worlds(self, worlds: list[int], seeds: list[int], options: dict | None) -> list[tuple[Any, dict]]:
        """Start the next episode of each world named (its last one ended, or the actor ended it),
        world worlds[k] from seeds[k]; each one's first (observation, info)."""

    def obstacles(self, i: int) -> list[tuple[float, float, float]]:
        """World i's obstacles this episode, (x, y, radius) each (the episode logger draws them)."""

    def close(self) -> None: ...


class EnvList:
    """Single envs, each with the actor's wrappers (action repeat, noise), stepped one by one."""

    def __init__(self, envs: list[gymnasium.Env]):
        self.envs = envs
        self.action_space, self.observation_space = envs[0].action_space, envs[0].observation_space

    def reset(self, seeds: list[int], options: dict | None) -> list[tuple[Any, dict]]:
        return [env.reset(seed=seed, options=options) for env, seed in zip(self.envs, seeds)]

    def step(self, actions: np.ndarray) -> list[Step]:
        return [env.step(action) for env, action in zip(self.envs, actions)]

    def reset_worlds(self, worlds: list[int], seeds: list[int], options: dict | None) -> list[tuple[Any, dict]]:
        return [self.envs[i].reset(seed=seed, options=options) for i, seed in zip(worlds, seeds)]

    def obstacles(self, i: int) -> list[tuple[float, float, float]]:
        return list(getattr(self.envs[i].unwrapped, "obstacles", []))

    def close(self) -> None:
        for env in self.envs:
            env.close()


class VectorWorlds:
    """The worlds of a gymnasium VectorEnv (autoreset DISABLED or SAME_STEP, see the module),
    each action taken ``repeat`` times.

    A world whose episode ends within the repeats has its reward summed up to the end, as
    `ActionRepeat` does. Its remaining repeats are stepped too (one call steps every world): a
    DISABLED env's are discarded before the world is reset; a SAME_STEP env's advance the world's
    next episode, whose first observation for the actor is then the one after them. With
    repeats, `info["inner_steps"]` counts the steps each world took in its episode."""

    def __init__(self, env: gymnasium.vector.VectorEnv, repeat: int = 1):
        mode = env.metadata.get("autoreset_mode")
        if mode not in (AutoresetMode.DISABLED, AutoresetMode.SAME_STEP):
            raise ValueError(f"a vector env for the actor autoresets its worlds in the same step or not at all; "
                             f"this one's autoreset mode is {mode}")
        self.env, self.repeat = env, repeat
        self.same_step = mode == AutoresetMode.SAME_STEP
        self.num_worlds = env.num_envs
        self.action_space, self.observation_space = env.single_action_space, env.single_observation_space
        self._latest: tuple[Any, dict] = (None, {})  # the batch observation and info of the last inner step

    def reset(self, seeds: list[int], options: dict | None) -> list[tuple[Any, dict]]:
        obs, info = self.env.reset(seed=list(seeds), options=options)
        self._latest = obs, info
        return [(world_of(obs, i), WorldInfo(info, i)) for i in range(self.num_worlds)]

    def step(self, actions: np.ndarray) -> list[Step]:
        n = self.num_worlds
        steps: list = [None] * n
        returns, inner_steps, ended = np.zeros(n), np.zeros(n, np.int64), np.zeros(n, bool)
        for _ in range(self.repeat):
            obs, reward, terminated, truncated, info = self.env.step(actions)
            running = ~ended
            returns[running] += reward[running]
            inner_steps[running] += 1
            done = running & (terminated | truncated)
            for i in np.flatnonzero(done):
                if self.same_step:
                    last_obs, last_info = world_of(info["final_obs"], i), info["final_info"]
                else:  # DISABLED: the world holds its last state until reset
                    last_obs, last_info = world_of(obs, i), info
                steps[i] = (last_obs, float(returns[i]), bool(terminated[i]), bool(truncated[i]),
                            self._counted(last_info, i, inner_steps[i]))
            ended |= done
        for i in np.flatnonzero(~ended):
            steps[i] = (world_of(obs, i), float(returns[i]), False, False, self._counted(info, i, inner_steps[i]))
        self._latest = obs, info
        return steps

    def _counted(self, info: dict, i: int, inner_steps: int) -> WorldInfo:
        return WorldInfo(info, i, {"inner_steps": int(inner_steps)} if self.repeat > 1 else None)

    def reset_worlds(self, worlds: list[int], seeds: list[int], options: dict | None) -> list[tuple[Any, dict]]:
        if not worlds:
            return []
        if self.same_step:
            # SAME_STEP: the env began each world's next episode itself. (Where the actor ended an
            # episode the env did not, a blow-up, the world can only go on from where it is.)
            obs, info = self._latest
        else:
            mask = np.zeros(self.num_worlds, bool)
            mask[worlds] = True
            per_world: list[int | None] = [None] * self.num_worlds
            for i, seed in zip(worlds, seeds):
                per_world[i] = seed
            obs, info = self.env.reset(seed=per_world, options={**(options or {}), "reset_mask": mask})
        return [(world_of(obs, i), WorldInfo(info, i)) for i in worlds]

    def obstacles(self, i: int) -> list[tuple[float, float, float]]:
        envs = getattr(self.env, "envs", None)  # a SyncVectorEnv's single envs
        if envs is not None:
            return list(getattr(envs[i].unwrapped, "obstacles", []))
        world_obstacles = getattr(self.env.unwrapped, "world_obstacles", None)  # an env's own (l2r/RunWarp-v0)
        return [] if world_obstacles is None else world_obstacles(i)

    def close(self) -> None:
        self.env.close()


def world_of(batch: Any, i: int) -> Any:
    """World i's item of a batched observation (an array, or a dict of arrays)."""
    return {name: world_of(value, i) for name, value in batch.items()} if isinstance(batch, dict) else batch[i]


class WorldInfo(Mapping):
    """World i's entries of a vector env's info: those its `_name` mask marks (every one without a
    mask), without the masks and the last state of an ended episode (`final_obs`, `final_info`),
    and `extra` entries of its own. Read when asked: most steps the actor reads one or two of a
    dozen entries, and a dict per world and step cost a quarter of its time."""

    __slots__ = ("_info", "_i", "_extra")

    def __init__(self, info: dict, i: int, extra: dict | None = None):
        self._info, self._i, self._extra = info, i, extra or {}

    def _has(self, name: str) -> bool:
        if name.startswith("_") or name in ("final_obs", "final_info") or name not in self._info:
            return False
        mask = self._info.get("_" + name)
        return mask is None or bool(mask[self._i])

    def __getitem__(self, name: str) -> Any:
        if name in self._extra:
            return self._extra[name]
        if not self._has(name):
            raise KeyError(name)
        value = self._info[name]
        return WorldInfo(value, self._i) if isinstance(value, dict) else value[self._i]

    def __iter__(self):
        yield from self._extra
        yield from (name for name in self._info if name not in self._extra and self._has(name))

    def __len__(self) -> int:
        return sum(1 for _ in self)

