"""`l2r/RunWarp-v0`: the Learning to Run env on MuJoCo Warp, N worlds in one call.

The observation, reward and done rules are `l2r/Run-v0`'s (`l2r.sim.env`), computed from the
same model and sensors; the physics is `WarpPhysics` (float32). `gymnasium.make_vec(ID,
num_envs=N)` gives `RunWarpVectorEnv`, which resets a finished world in the same step (its
observation is the new episode's first; `info["final_obs"]` holds the last), or, with
`autoreset_mode=DISABLED`, only when asked through gymnasium's masked reset, each world with the
seed and difficulty it is given (as an actor resets its single envs); `gymnasium.make(ID)` gives
`RunWarpEnv`, one world with the single-env API.

Difficulties 1 and 2 draw each world's obstacles and psoas strengths as `l2r/Run-v0` does, from
a generator per world seeded as gymnasium seeds a vector env's worlds (world w: seed + w), so a
world's episodes are those of `RunEnv` reset with that seed. Each world's obstacles push its
feet as the port's do (`l2r.sim.contact`, OpenSim's law), and are drawn as the model's three
sphere geoms in that world's row of MuJoCo Warp's per-world geom fields. A world whose state turns
non-finite ends its episode with reward 0 and `info["diverged"]` (MuJoCo Warp resets no world on
its own and counts no warnings per world).

`randomize` is `l2r/Run-v0`'s (`l2r.sim.randomize`): each world's episodes draw their body from
the world's generator after the course, as `RunEnv` does, so world w's bodies are those of
`RunEnv` reset with its seed; `randomized[w]` holds world w's draws.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import mujoco
import numpy as np
import warp as wp

from l2r.sim import model as body
from l2r.sim import thelen
from l2r.sim.env import (FALL_HEIGHT, LIGAMENT_PENALTY, MAX_STEPS, NO_OBSTACLE, NUM_MUSCLES, NUM_OBSTACLES,
                         PSOAS_RIGHT, STEP_SECONDS, check_arguments, check_difficulty, draw_episode, sensor_gathers,
                         subtree_masses, with_sensors)
from l2r.sim.contact import contact_law
from l2r.sim.layout import OBS_SIZE
from l2r.sim.ligaments import LIGAMENTS
from l2r.sim.opensim import read_osim
from l2r.sim.randomize import CONTACT_FIELDS, Randomization
from l2r.sim.warp.physics import WarpPhysics


class RunWarpVectorEnv(gym.vector.VectorEnv):
    """`num_envs` runners stepped together on a Warp device.

    device: a Warp device ("cpu", "cuda", "cuda:1"); None takes Warp's default (a GPU when there
        is one).
    graphs: replay each physics step's and reset's launches as one captured Warp graph (the
        default); False launches every kernel from Python each time.
    autoreset_mode: SAME_STEP (the default) begins a finished world's next episode in the step
        that ends it; DISABLED leaves it until `reset(seed=[...], options={"reset_mask": mask})`
        (a finished world goes on stepping meanwhile; what it does then means nothing).
    The other arguments are `RunEnv`'s.
    """

    metadata = {"autoreset_mode": gym.vector.AutoresetMode.SAME_STEP}
    AUTORESET_MODES = (gym.vector.AutoresetMode.SAME_STEP, gym.vector.AutoresetMode.DISABLED)

    def __init__(self, num_envs: int = 1, difficulty: int = 0, seed: int | None = None,
                 left_psoas: str = "glut_max_l", max_steps: int = MAX_STEPS, device: str | None = None,
                 graphs: bool = True, autoreset_mode: gym.vector.AutoresetMode | str = gym.vector.AutoresetMode.SAME_STEP,
                 randomize: Randomization | dict[str, float] | None = None):
        check_arguments(difficulty, left_psoas, max_steps)
        self.randomize = Randomization.of(randomize)
        if num_envs < 1:
            raise ValueError(f"num_envs must be at least 1, got {num_envs}")
        mode = gym.vector.AutoresetMode(autoreset_mode)
        if mode not in self.AUTORESET_MODES:
            raise ValueError(f"autoreset_mode must be one of {', '.join(m.value for m in self.AUTORESET_MODES)}; got {mode.value}")
        self.metadata = {**self.metadata, "autoreset_mode": mode}
        self.num_envs, self.max_steps, self._seed = num_envs, max_steps, seed
        self.difficulties = np.full(num_envs, difficulty)  # each world's, for its episodes' draws
        self.left_psoas = left_psoas
        self.device = wp.get_device(device)
        m = with_sensors(mujoco.MjSpec.from_file(str(body.MODEL_PATH)))
        self.substeps = round(STEP_SECONDS / m.opt.timestep)
        self._obs_gather = sensor_gathers(m)
        self._x_adr, self._y_adr = (int(m.joint(c).qposadr[0]) for c in ("pelvis_tx", "pelvis_ty"))
        self.muscle_names, self.ligament_names = tuple(body.MUSCLES), LIGAMENTS
        self.body_names = tuple(m.body(i).name for i in range(m.nbody))  # the rows of info["body_pos"]
        self._psoas = [self.muscle_names.index(left_psoas), self.muscle_names.index(PSOAS_RIGHT)]
        osim = read_osim(body.OSIM_PATH)
        by_name = {mu.name: mu for mu in osim.muscles}
        with wp.ScopedDevice(self.device):
            self._physics = WarpPhysics(m, osim, [by_name[n] for n in body.MUSCLES], num_envs,
                                        m.keyframe(body.DEFAULT_KEYFRAME).id, graphs,
                                        per_world_bodies=self.randomize.mass > 0)
        # The body as the model has it, which randomisation scales per episode and world; host
        # copies of the per-world arrays that randomisation writes, each assigned whole.
        self._model, self._contact_law = m, contact_law(osim)
        self._contact_tables = np.tile(self._contact_law.table(), (num_envs, 1))
        self._bodies = {name: np.tile(getattr(m, name), (num_envs,) + (1,) * getattr(m, name).ndim)
                        for name in ("body_mass", "body_inertia", "body_subtreemass")}
        self._parked = self._physics.obstacles.numpy()[0].astype(np.float64)  # (x, y, r) of the unused spheres
        physics, data = self._physics, self._physics.data
        self._state = HostState(self.device, {
            "qpos": data.qpos, "sensordata": data.sensordata, "xpos": data.xpos, "xquat": data.xquat,
            "obstacle_force": physics.obstacle_force, "ground_force": physics.ground_force,
            "activation": physics.activation, "muscle_length": physics.muscle_length,
            "muscle_force": physics.muscle_force, "fiber": physics.fiber, "ligament_force": physics.ligament_force})

        self.single_action_space = gym.spaces.Box(0.0, 1.0, shape=(NUM_MUSCLES,), dtype=np.float32)
        self.single_observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(OBS_SIZE,), dtype=np.float32)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, num_envs)
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, num_envs)
        self._steps = np.zeros(num_envs, dtype=np.int64)
        self._x = np.zeros(num_envs)
        self._rngs: list[np.random.Generator] = []  # each world's, for its episodes' draws
        # This episode's obstacles (world, obstacle, (x, y, r)), sorted by x, NaN where there is
        # none, and psoas strengths (world, (left, right)).
        self.obstacles = np.full((num_envs, NUM_OBSTACLES, 3), np.nan)
        self.psoas = np.ones((num_envs, 2))
        self.randomized: list[dict[str, Any]] = [{} for _ in range(num_envs)]  # each world's draws this episode
        # (world, muscle): this episode's randomised strength, fibre and slack length factors
        self._muscle_factors = {name: np.ones((num_envs, NUM_MUSCLES)) for name in ("strength", "fiber_length",
                                                                                      "tendon_slack")}

    def world_obstacles(self, w: int) -> list[tuple[float, float, float]]:
        """World w's obstacles this episode, (x, y, radius) sorted by x, as `RunEnv.obstacles`."""
        return [(x, y, r) for x, y, r in self.obstacles[w].tolist() if not np.isnan(x)]

    @property
    def max_isometric_force(self) -> np.ndarray:
        """Each world's max isometric forces (N) this episode, psoas strengths applied, (world, muscle)."""
        return self._physics.params.numpy()[:, :, thelen.MAX_FORCE].astype(np.float64)

    def reset(self, *, seed: int | list[int | None] | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        """Start a new episode in every world (or those `options["reset_mask"]` marks): the
        default pose at rest, with a new obstacle course and psoas strengths. seed: an int seeds
        world w with seed + w, a list one seed per world (None: that world goes on with its
        generator); None (after the constructor's seed) goes on with each world's generator.

        options: {"difficulty": 0|1|2} changes the difficulty of the worlds reset from this
        episode on; {"reset_mask": bool array of num_envs} resets only the worlds it marks (the
        others go on as they are). The observation and info are every world's.
        """
        worlds = np.arange(self.num_envs)
        if options and options.get("reset_mask") is not None:
            mask = np.asarray(options["reset_mask"])
            if mask.shape != (self.num_envs,) or mask.dtype != bool:
                raise ValueError(f"reset_mask must be a bool array of shape ({self.num_envs},); got {mask.dtype} {mask.shape}")
            if not self._rngs:
                raise ValueError("a masked reset needs a first reset of every world")
            worlds = np.flatnonzero(mask)
        if seed is None:
            seed, self._seed = self._seed, None
        seeds = seed if isinstance(seed, list) else [None if seed is None else seed + w for w in range(self.num_envs)]
        if len(seeds) != self.num_envs:
            raise ValueError(f"reset(seed=...) takes one seed per world ({self.num_envs}); got {len(seeds)}")
        if len(worlds) == self.num_envs:
            super().reset(seed=seeds[0])
        if not self._rngs:
            self._rngs = [gym.utils.seeding.np_random(s)[0] for s in seeds]
        else:
            for w in worlds:
                if seeds[w] is not None:
                    self._rngs[w] = gym.utils.seeding.np_random(seeds[w])[0]
        if options and "difficulty" in options:
            check_difficulty(options["difficulty"])
            self.difficulties[worlds] = options["difficulty"]
        self._draw_episodes(worlds)
        with wp.ScopedDevice(self.device):
            self._physics.reset(None if len(worlds) == self.num_envs else worlds)
        self._steps[worlds] = 0
        state = self._state.fetch()
        self._x[worlds] = state["qpos"][worlds, self._x_adr]
        return self._observe(state), self._info(state)

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict]:
        """Advance every world 0.01 s; excitations are clipped to [0, 1]; NaN, inf or a shape
        other than (num_envs, 18) raise ValueError."""
        a = np.asarray(actions, dtype=np.float32)
        if a.shape != (self.num_envs, NUM_MUSCLES):
            raise ValueError(f"actions must have shape ({self.num_envs}, {NUM_MUSCLES}); got {a.shape}")
        if not np.isfinite(a).all():
            raise ValueError("actions contain NaN or inf")
        physics = self._physics
        with wp.ScopedDevice(self.device):
            physics.next_excitation.assign(a.clip(0.0, 1.0))
            physics.step(self.substeps)
        self._steps += 1
        state = self._state.fetch()
        x_before, self._x = self._x, state["qpos"][:, self._x_adr].astype(np.float64)
        obs, info = self._observe(state), self._info(state)
        ligaments = info["ligament_force"]
        reward = (self._x - x_before) - np.sqrt((ligaments * ligaments).sum(axis=1)) * LIGAMENT_PENALTY
        diverged = ~np.isfinite(obs).all(axis=1)
        terminated = (state["qpos"][:, self._y_adr] < FALL_HEIGHT) | diverged
        reward[diverged] = 0.0
        info["diverged"] = diverged
        truncated = self._steps >= self.max_steps
        done = terminated | truncated
        if done.any() and self.metadata["autoreset_mode"] == gym.vector.AutoresetMode.SAME_STEP:
            info["final_obs"], info["final_info"] = obs.copy(), dict(info)
            info["_final_obs"] = info["_final_info"] = done  # which worlds' entries hold a last state
            worlds = np.flatnonzero(done)
            self._draw_episodes(worlds)
            with wp.ScopedDevice(self.device):
                physics.reset(worlds)
            self._steps[worlds] = 0
            state = self._state.fetch()
            self._x[worlds] = state["qpos"][worlds, self._x_adr]
            obs[worlds] = self._observe(state)[worlds]
            for name, value in self._info(state).items():  # a reset world's info is its new episode's, as its obs
                value[~done] = info[name][~done]
                info[name] = value
        return obs, reward, terminated, truncated, info

    def _draw_episodes(self, worlds) -> None:
        """The next episode's obstacles, psoas strengths and (randomised) body of the worlds
        named, each drawn from its world's generator as `RunEnv` draws them, into the physics'
        per-world arrays (which the worlds take when reset)."""
        for w in worlds:
            course, self.psoas[w] = draw_episode(self._rngs[w], int(self.difficulties[w]))
            self.obstacles[w] = np.nan
            self.obstacles[w, :len(course)] = np.reshape(course, (-1, 3))
            if self.randomize:
                self.randomized[w] = self.randomize.draw(self._rngs[w], NUM_MUSCLES, self._model.nbody - 1)
        physics = self._physics
        physics.obstacles.assign(np.where(np.isnan(self.obstacles), self._parked, self.obstacles).astype(np.float32))
        if self.randomize:
            self._randomize_bodies(worlds)
        strength = self._muscle_factors["strength"].copy()
        strength[:, self._psoas] *= self.psoas
        physics.strength.assign(strength.astype(np.float32))

    def _randomize_bodies(self, worlds) -> None:
        """The randomised worlds' bodies: the default one scaled by each world's draws (as
        `RunEnv._randomize_body` scales it), into the physics' per-world arrays."""
        physics, model = self._physics, self._physics.model
        for w in worlds:
            drawn = self.randomized[w]
            for name, factors in self._muscle_factors.items():
                factors[w] = drawn.get(name, 1.0)
        for name, array in (("fiber_length", physics.fiber_scale), ("tendon_slack", physics.slack_scale)):
            array.assign(self._muscle_factors[name].astype(np.float32))
        delay = np.array([int(self.randomized[w].get("delay", False)) for w in range(self.num_envs)], np.int32)
        physics.delay.assign(delay)
        if any(getattr(self.randomize, name) for name in CONTACT_FIELDS):
            for w in worlds:
                factors = (self.randomized[w].get(name, 1.0) for name in CONTACT_FIELDS)
                self._contact_tables[w] = self._contact_law.scaled(*factors).table()
            physics.contact_law.assign(self._contact_tables.astype(np.float32))
        if self.randomize.mass:
            m, bodies = self._model, self._bodies
            for w in worlds:
                factors = self.randomized[w]["mass"]
                bodies["body_mass"][w, 1:] = m.body_mass[1:] * factors
                bodies["body_inertia"][w, 1:] = m.body_inertia[1:] * factors[:, None]
                bodies["body_subtreemass"][w] = subtree_masses(bodies["body_mass"][w], m.body_parentid)
            for name, array in bodies.items():
                getattr(model, name).assign(array.astype(np.float32))

    def _observe(self, state: dict[str, np.ndarray]) -> np.ndarray:
        obs = np.empty((self.num_envs, OBS_SIZE), dtype=np.float32)
        obs[:, :36] = state["sensordata"][:, self._obs_gather]
        obs[:, 36:38] = self.psoas
        obs[:, 38:] = next_obstacles(self.obstacles, self._x)
        return obs

    def _info(self, state: dict[str, np.ndarray]) -> dict[str, Any]:
        contact = state["obstacle_force"].astype(np.float64)
        contact[:, :, :2] += state["ground_force"]
        return {"distance": state["qpos"][:, self._x_adr].astype(np.float64),
                **{name: state[field].astype(np.float64) for name, field in INFO_FIELDS.items()},
                "contact_force": contact}


class HostState:
    """The device arrays the env reads after a step or reset, brought to the host together: on a
    GPU each is copied into pinned host memory and the host waits once for all of them, where
    reading each with `.numpy()` waited once per array, a dozen waits a step (each one a turn of
    the GPU to take, when other processes share it). On the CPU the arrays are read in place.
    What `fetch` returns is valid until the next fetch."""

    def __init__(self, device: wp.Device, arrays: dict[str, wp.array]):
        self.device, self.arrays = device, arrays
        self.pinned = {name: wp.empty(a.shape, dtype=a.dtype, device="cpu", pinned=True)
                       for name, a in arrays.items()} if device.is_cuda else None

    def fetch(self) -> dict[str, np.ndarray]:
        if self.pinned is None:
            return {name: a.numpy() for name, a in self.arrays.items()}
        for name, a in self.arrays.items():
            wp.copy(self.pinned[name], a)
        wp.synchronize_device(self.device)
        return {name: host.numpy() for name, host in self.pinned.items()}


class RunWarpEnv(gym.Env):
    """One runner on a Warp device with the single-env API of `l2r/Run-v0` (arguments as
    `RunWarpVectorEnv`'s)."""

    metadata = {"render_modes": []}

    def __init__(self, difficulty: int = 0, seed: int | None = None, left_psoas: str = "glut_max_l",
                 max_steps: int = MAX_STEPS, device: str | None = None, graphs: bool = True,
                 randomize: Randomization | dict[str, float] | None = None):
        self._worlds = RunWarpVectorEnv(1, difficulty, seed, left_psoas, max_steps, device, graphs,
                                        randomize=randomize)
        self.muscle_names, self.ligament_names = self._worlds.muscle_names, self._worlds.ligament_names
        self.body_names = self._worlds.body_names
        self.action_space = self._worlds.single_action_space
        self.observation_space = self._worlds.single_observation_space
        self._running = False

    @property
    def obstacles(self) -> list[tuple[float, float, float]]:
        """This episode's obstacles, (x, y, radius) sorted by x, as `RunEnv.obstacles`."""
        return self._worlds.world_obstacles(0)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        obs, info = self._worlds.reset(seed=seed, options=options)
        self._running = True
        info = _world(info, 0)
        if self._worlds.randomize:  # as RunEnv's
            info["randomization"] = self._worlds.randomized[0]
        return obs[0], info

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if not self._running:
            raise RuntimeError("RunWarpEnv.step() needs reset() first, and again after an episode ends")
        a = np.asarray(action, dtype=np.float32)
        if a.shape != (NUM_MUSCLES,):
            raise ValueError(f"action must have shape ({NUM_MUSCLES},), one excitation per muscle; got {a.shape}")
        obs, reward, terminated, truncated, info = self._worlds.step(a[None])
        done = bool(terminated[0] or truncated[0])
        self._running = not done
        if done:  # the vector env has already begun the next episode: report the last state
            obs, info = info["final_obs"], info["final_info"]
        return obs[0], float(reward[0]), bool(terminated[0]), bool(truncated[0]), _world(info, 0)


# info entries read from one state array each (HostState's names)
INFO_FIELDS = {"body_pos": "xpos", "body_quat": "xquat", "muscle_activation": "activation",
               "muscle_length": "muscle_length", "muscle_force": "muscle_force", "fiber_length": "fiber",
               "ligament_force": "ligament_force"}


def next_obstacles(obstacles: np.ndarray, pelvis_x: np.ndarray) -> np.ndarray:
    """`next_obstacle` of each world: obstacles (world, obstacle, (x, y, r)) sorted by x, NaN
    rows where there is none; (x - pelvis x, y, r) of the first not behind the pelvis, or
    `NO_OBSTACLE`."""
    ahead = obstacles[:, :, 0] + obstacles[:, :, 2] >= pelvis_x[:, None]  # False for NaN rows
    found = ahead.any(axis=1)
    nearest = obstacles[np.arange(len(obstacles)), ahead.argmax(axis=1)]
    nearest[:, 0] -= pelvis_x
    return np.where(found[:, None], nearest, NO_OBSTACLE)


def _world(info: dict[str, Any], w: int) -> dict[str, Any]:
    return {k: (v[w] if isinstance(v, np.ndarray) else v) for k, v in info.items() if not k.lstrip("_").startswith("final_")}
