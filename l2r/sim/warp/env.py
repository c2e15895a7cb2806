"""`l2r/RunWarp-v0`: the Learning to Run env on MuJoCo Warp, N worlds in one call.

The observation, reward and done rules are `l2r/Run-v0`'s (`l2r.sim.env`), computed from the
same model and sensors; the physics is `WarpPhysics` (float32). `gymnasium.make_vec(ID,
num_envs=N)` gives `RunWarpVectorEnv`, which resets a finished world in the same step (its
observation is the new episode's first; `info["final_obs"]` holds the last); `gymnasium.make(ID)`
gives `RunWarpEnv`, one world with the single-env API.

Only difficulty 0 (flat ground) so far: the obstacles need per-world geoms and MuJoCo Warp's
contacts. A world whose state turns non-finite ends its episode with reward 0 and
`info["diverged"]` (MuJoCo Warp resets no world on its own and counts no warnings per world).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import mujoco
import numpy as np
import warp as wp

from l2r.sim import model as body
from l2r.sim.env import (FALL_HEIGHT, LIGAMENT_PENALTY, MAX_STEPS, NO_CONTACTS, NO_OBSTACLE, NUM_MUSCLES, STEP_SECONDS,
                         check_arguments, sensor_gathers, with_sensors)
from l2r.sim.layout import OBS_SIZE
from l2r.sim.ligaments import LIGAMENTS
from l2r.sim.opensim import read_osim
from l2r.sim.warp.physics import WarpPhysics


class RunWarpVectorEnv(gym.vector.VectorEnv):
    """`num_envs` runners stepped together on a Warp device.

    device: a Warp device ("cpu", "cuda", "cuda:1"); None takes Warp's default (a GPU when there
        is one). The other arguments are `RunEnv`'s; difficulty must be 0.
    """

    metadata = {"autoreset_mode": gym.vector.AutoresetMode.SAME_STEP}

    def __init__(self, num_envs: int = 1, difficulty: int = 0, seed: int | None = None,
                 left_psoas: str = "glut_max_l", max_steps: int = MAX_STEPS, device: str | None = None):
        check_arguments(difficulty, left_psoas, max_steps)
        if difficulty != 0:
            raise ValueError(f"l2r/RunWarp-v0 runs difficulty 0 only (no obstacles yet), got {difficulty}")
        if num_envs < 1:
            raise ValueError(f"num_envs must be at least 1, got {num_envs}")
        self.num_envs, self.difficulty, self.max_steps, self._seed = num_envs, difficulty, max_steps, seed
        self.device = wp.get_device(device)
        m = with_sensors(mujoco.MjSpec.from_file(str(body.MODEL_PATH)))
        m.opt.disableflags |= NO_CONTACTS  # no obstacles: nothing MuJoCo could find to collide
        self.substeps = round(STEP_SECONDS / m.opt.timestep)
        self._obs_gather, _ = sensor_gathers(m)
        self._x_adr, self._y_adr = (int(m.joint(c).qposadr[0]) for c in ("pelvis_tx", "pelvis_ty"))
        self.muscle_names, self.ligament_names = tuple(body.MUSCLES), LIGAMENTS
        self.body_names = tuple(m.body(i).name for i in range(m.nbody))  # the rows of info["body_pos"]
        osim = read_osim(body.OSIM_PATH)
        by_name = {mu.name: mu for mu in osim.muscles}
        with wp.ScopedDevice(self.device):
            self._physics = WarpPhysics(m, osim, [by_name[n] for n in body.MUSCLES], num_envs,
                                        m.keyframe(body.DEFAULT_KEYFRAME).id)

        self.single_action_space = gym.spaces.Box(0.0, 1.0, shape=(NUM_MUSCLES,), dtype=np.float32)
        self.single_observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(OBS_SIZE,), dtype=np.float32)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, num_envs)
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, num_envs)
        self._steps = np.zeros(num_envs, dtype=np.int64)
        self._x = np.zeros(num_envs)

    def reset(self, *, seed: int | list[int] | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        """Every world from the default pose at rest (difficulty 0 draws nothing: no obstacles,
        psoas strengths 1)."""
        if seed is None:
            seed, self._seed = self._seed, None
        super().reset(seed=seed if not isinstance(seed, list) else seed[0])
        with wp.ScopedDevice(self.device):
            self._physics.reset()
        self._steps[:] = 0
        qpos = self._physics.data.qpos.numpy()
        self._x = qpos[:, self._x_adr].astype(np.float64)
        return self._observe(), self._info(qpos)

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
            physics.excitation.assign(a.clip(0.0, 1.0))
            physics.step(self.substeps)
        self._steps += 1
        qpos = physics.data.qpos.numpy()
        x_before, self._x = self._x, qpos[:, self._x_adr].astype(np.float64)
        ligaments = physics.ligament_force.numpy().astype(np.float64)
        reward = (self._x - x_before) - np.sqrt((ligaments * ligaments).sum(axis=1)) * LIGAMENT_PENALTY
        obs, info = self._observe(), self._info(qpos)
        diverged = ~np.isfinite(obs).all(axis=1)
        terminated = (qpos[:, self._y_adr] < FALL_HEIGHT) | diverged
        reward[diverged] = 0.0
        info["diverged"] = diverged
        truncated = self._steps >= self.max_steps
        done = terminated | truncated
        if done.any():
            info["final_obs"], info["final_info"] = obs.copy(), dict(info)
            info["_final_obs"] = info["_final_info"] = done  # which worlds' entries hold a last state
            worlds = np.flatnonzero(done)
            with wp.ScopedDevice(self.device):
                physics.reset(worlds)
            self._steps[worlds] = 0
            qpos = physics.data.qpos.numpy()
            self._x[worlds] = qpos[worlds, self._x_adr]
            obs[worlds] = self._observe()[worlds]
            for name, value in self._info(qpos).items():  # a reset world's info is its new episode's, as its obs
                value[~done] = info[name][~done]
                info[name] = value
        return obs, reward, terminated, truncated, info

    def _observe(self) -> np.ndarray:
        obs = np.empty((self.num_envs, OBS_SIZE), dtype=np.float32)
        obs[:, :36] = self._physics.data.sensordata.numpy()[:, self._obs_gather]
        obs[:, 36:38] = 1.0  # psoas strengths (left, right): drawn at difficulty 2 only
        obs[:, 38:] = NO_OBSTACLE
        return obs

    def _info(self, qpos: np.ndarray) -> dict[str, Any]:
        physics = self._physics
        ground = physics.ground_force.numpy().astype(np.float64)
        contact = np.zeros((self.num_envs, len(body.CONTACT_SPHERES), 3))
        contact[:, :, :2] = ground
        data = physics.data
        return {
            "distance": qpos[:, self._x_adr].astype(np.float64),
            "body_pos": data.xpos.numpy().astype(np.float64),
            "body_quat": data.xquat.numpy().astype(np.float64),
            "muscle_activation": physics.activation.numpy().astype(np.float64),
            "muscle_length": physics.muscle_length.numpy().astype(np.float64),
            "muscle_force": physics.muscle_force.numpy().astype(np.float64),
            "fiber_length": physics.fiber.numpy().astype(np.float64),
            "ligament_force": physics.ligament_force.numpy().astype(np.float64),
            "contact_force": contact,
        }


class RunWarpEnv(gym.Env):
    """One runner on a Warp device with the single-env API of `l2r/Run-v0` (arguments as
    `RunWarpVectorEnv`'s)."""

    metadata = {"render_modes": []}

    def __init__(self, difficulty: int = 0, seed: int | None = None, left_psoas: str = "glut_max_l",
                 max_steps: int = MAX_STEPS, device: str | None = None):
        self._worlds = RunWarpVectorEnv(1, difficulty, seed, left_psoas, max_steps, device)
        self.muscle_names, self.ligament_names = self._worlds.muscle_names, self._worlds.ligament_names
        self.body_names = self._worlds.body_names
        self.action_space = self._worlds.single_action_space
        self.observation_space = self._worlds.single_observation_space
        self._running = False

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        obs, info = self._worlds.reset(seed=seed, options=options)
        self._running = True
        return obs[0], _world(info, 0)

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


def _world(info: dict[str, Any], w: int) -> dict[str, Any]:
    return {k: (v[w] if isinstance(v, np.ndarray) else v) for k, v in info.items() if not k.lstrip("_").startswith("final_")}
