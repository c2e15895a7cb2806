"""`RunEnv`: the NeurIPS 2017 Learning to Run environment on the MuJoCo body.

One step is 0.01 s of simulated time: the 18 excitations are held while MuJoCo takes the
physics substeps, and the six joint-limit ligaments (`ligaments.py`) are recomputed from the
state before every substep, as OpenSim evaluates its `CoordinateLimitForce`s inside its
integrator. The observation, reward, done rules and episode generation follow the 2017
`RunEnv` (see docs/environment.md for the observation table and the choices made).
"""

from __future__ import annotations

import math
import operator
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np

from l2r.sim import model as body
from l2r.sim.ligaments import LIGAMENTS, LigamentKernel, default_limits

STEP_SECONDS = 0.01
MAX_STEPS = 1000
FALL_HEIGHT = 0.65  # m; the episode ends when the pelvis drops below this
LIGAMENT_PENALTY = 1e-7  # per N·m of the ligament forces' Euclidean norm
NUM_OBSTACLES = 3
NO_OBSTACLE = (100.0, 0.0, 0.0)  # what the 2017 env reports when no obstacle lies ahead

PELVIS = ("pelvis_tilt", "pelvis_tx", "pelvis_ty")
JOINTS = ("hip_flexion_r", "knee_angle_r", "ankle_angle_r", "hip_flexion_l", "knee_angle_l", "ankle_angle_l")
TRACKED_BODIES = ("head", "pelvis", "torso", "toes_l", "toes_r", "talus_l", "talus_r")
FOOT_SPHERES = ("r_heel", "r_toe", "l_heel", "l_toe")
PSOAS_RIGHT = "iliopsoas_r"
# The 2017 code scaled muscle index 11 for the left psoas, which is glut_max_l;
# "iliopsoas_l" applies the left strength to the muscle it was meant for.
LEFT_PSOAS_CHOICES = ("glut_max_l", "iliopsoas_l")

OBS_SIZE = 41
OBS_PSOAS = slice(36, 38)
OBS_OBSTACLE = slice(38, 41)


def _require_reset(*_: Any) -> None:
    raise RuntimeError("RunEnv.step() called before reset() or after the episode ended; call reset()")


class RunEnv(gym.Env):
    """Run as far as possible in 1000 steps of 0.01 s, driving 18 muscles.

    difficulty: 0 flat ground; 1 three sphere obstacles; 2 obstacles and random psoas strengths.
    seed: seeds the first `reset()` (a `reset(seed=...)` overrides it).
    left_psoas: the muscle the left psoas strength scales at difficulty 2: "glut_max_l" (the
        2017 code's index 11, the default, so results compare with 2017) or "iliopsoas_l".
    max_steps: truncation length (1000 in 2017).
    """

    metadata = {"render_modes": []}

    def __init__(
        self,
        difficulty: int = 0,
        seed: int | None = None,
        left_psoas: str = "glut_max_l",
        max_steps: int = MAX_STEPS,
    ):
        if difficulty not in (0, 1, 2):
            raise ValueError(f"difficulty must be 0, 1 or 2, got {difficulty!r}")
        if left_psoas not in LEFT_PSOAS_CHOICES:
            raise ValueError(f"left_psoas must be one of {LEFT_PSOAS_CHOICES}, got {left_psoas!r}")
        if max_steps < 1:
            raise ValueError(f"max_steps must be positive, got {max_steps}")
        self.difficulty = difficulty
        self.left_psoas = left_psoas
        self.max_steps = max_steps
        self._seed = seed

        m = body.load_model()
        d = mujoco.MjData(m)
        self._m, self._d = m, d
        self.muscle_names = tuple(body.MUSCLES)
        self.body_names = tuple(m.body(i).name for i in range(m.nbody))
        n_sub = STEP_SECONDS / m.opt.timestep
        self.substeps = round(n_sub)
        if abs(n_sub - self.substeps) > 1e-9 or self.substeps < 1:
            raise ValueError(f"model timestep {m.opt.timestep} does not divide {STEP_SECONDS} s")

        def joint(name: str) -> int:
            return mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name)

        # Index arrays, computed once; the step never looks a name up.
        coords = PELVIS[:3] + JOINTS
        qadr = np.array([m.jnt_qposadr[joint(c)] for c in coords])
        vadr = np.array([m.jnt_dofadr[joint(c)] for c in coords])
        self._pelvis_x_adr = int(qadr[1])
        self._pelvis_y_adr = int(qadr[2])
        lig = default_limits()
        self._lig_kernel = LigamentKernel(lig)
        self._lig_q = operator.itemgetter(*[int(m.jnt_qposadr[joint(c)]) for c in lig.coordinates])
        self._lig_v = operator.itemgetter(*[int(m.jnt_dofadr[joint(c)]) for c in lig.coordinates])
        self._lig_dofs = [int(m.jnt_dofadr[joint(c)]) for c in lig.coordinates]
        self.ligament_names = LIGAMENTS

        # Observation values 0..35 gathered in one `take` from [qpos, qvel, com, com vel, xpos].
        nq, nv = m.nq, m.nv
        com, comvel, xpos = nq + nv, nq + nv + 3, nq + nv + 6
        body_ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, b) for b in TRACKED_BODIES]
        self._obs_gather = np.concatenate(
            [
                qadr[:3], nq + vadr[:3], qadr[3:], nq + vadr[3:],
                [com, com + 1, comvel, comvel + 1],
                np.ravel([[xpos + 3 * b, xpos + 3 * b + 1] for b in body_ids]),
            ]
        )  # fmt: skip
        self._state = np.empty(nq + nv + 6 + 3 * m.nbody)
        self._obs = np.empty(OBS_SIZE, dtype=np.float32)

        # Muscles: the actuators in action order; muscle state lives in act at actuator_actadr.
        act_ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, n) for n in self.muscle_names]
        if act_ids != list(range(m.nu)) or m.nu != 18:
            raise ValueError("the model's actuators must be the 18 muscles in action order")
        self._act_adr = m.actuator_actadr.copy()
        self._psoas_ids = (self.muscle_names.index(PSOAS_RIGHT), self.muscle_names.index(left_psoas))
        self._base_force = m.actuator_gainprm[:, 2].copy()

        # Obstacles: three world spheres, parked where the model put them until an episode uses them.
        self._obstacle_geoms = [
            mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, f"obstacle_{i}") for i in range(NUM_OBSTACLES)
        ]
        self._parked = [(m.geom_pos[g].copy(), float(m.geom_size[g, 0])) for g in self._obstacle_geoms]

        # Contacts: geom id -> foot sphere slot (-1 for any other geom).
        self._foot_slot = np.full(m.ngeom, -1)
        for slot, name in enumerate(FOOT_SPHERES):
            self._foot_slot[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, name)] = slot
        self._contact_force = np.zeros((len(FOOT_SPHERES), 3))

        self.action_space = gym.spaces.Box(0.0, 1.0, shape=(m.nu,), dtype=np.float32)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(OBS_SIZE,), dtype=np.float32)

        self.obstacles: list[tuple[float, float, float]] = []
        self.psoas = (1.0, 1.0)  # strength (left, right), as the observation reports it
        self._steps = 0
        self._lig_force = [0.0] * len(LIGAMENTS)
        self._step_impl = _require_reset

    # Read-only access for the validator and loggers: mutate the simulation through the env only.
    @property
    def model(self) -> mujoco.MjModel:
        return self._m

    @property
    def data(self) -> mujoco.MjData:
        return self._d

    # ----------------------------------------------------------------------------------- episode

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Start an episode: default pose, a new obstacle course and psoas strengths.

        options: {"difficulty": 0|1|2} changes the difficulty from this episode on.
        """
        if seed is None and self._seed is not None:
            seed, self._seed = self._seed, None
        super().reset(seed=seed)
        if options and "difficulty" in options:
            if options["difficulty"] not in (0, 1, 2):
                raise ValueError(f"difficulty must be 0, 1 or 2, got {options['difficulty']!r}")
            self.difficulty = options["difficulty"]

        m, d = self._m, self._d
        self.obstacles, self.psoas = draw_episode(self.np_random, self.difficulty)
        self._place_obstacles()
        left, right = self.psoas
        m.actuator_gainprm[:, 2] = self._base_force
        m.actuator_gainprm[self._psoas_ids[0], 2] *= right
        m.actuator_gainprm[self._psoas_ids[1], 2] *= left
        m.actuator_biasprm[:, 2] = m.actuator_gainprm[:, 2]

        mujoco.mj_resetData(m, d)
        mujoco.mj_forward(m, d)
        self._after_physics()
        self._lig_force = self._lig_kernel(self._lig_q(d.qpos.tolist()), self._lig_v(d.qvel.tolist()))
        self._steps = 0
        self._step_impl = self._step
        self._contact_force[:] = 0.0
        obs = self._observe()
        return obs.copy(), self._info()

    def _place_obstacles(self) -> None:
        m = self._m
        for i, g in enumerate(self._obstacle_geoms):
            if i < len(self.obstacles):
                x, y, r = self.obstacles[i]
                pos = (x, y, 0.0)
            else:
                pos, r = self._parked[i]
            m.geom_pos[g] = pos
            m.geom_size[g, 0] = r
            m.geom_rbound[g] = r
            m.geom_aabb[g, 3:] = r  # the broad phase reads the local box, not only rbound

    # -------------------------------------------------------------------------------------- step

    def step(self, action):
        """Advance 0.01 s. Excitations outside [0, 1] are clipped; NaN, inf or a wrong shape
        raise ValueError."""
        return self._step_impl(action)

    def _step(self, action):
        a = np.asarray(action, dtype=np.float64)
        if a.shape != (18,):
            raise ValueError(f"action must have shape (18,) (one excitation per muscle), got {a.shape}")
        if not np.isfinite(a).all():
            raise ValueError(f"action contains NaN or inf: {a.tolist()}")
        m, d = self._m, self._d
        np.clip(a, 0.0, 1.0, out=d.ctrl)

        x_before = d.qpos[self._pelvis_x_adr]
        qfrc, dofs, kernel = d.qfrc_applied, self._lig_dofs, self._lig_kernel
        forces = self._lig_force
        for i in range(self.substeps):
            for dof, f in zip(dofs, forces):
                qfrc[dof] = f
            mujoco.mj_step2(m, d)
            if i == self.substeps - 1:
                self._record_contacts()
            mujoco.mj_step1(m, d)
            qpos, qvel = d.qpos.tolist(), d.qvel.tolist()
            forces = kernel(self._lig_q(qpos), self._lig_v(qvel))
        self._lig_force = forces
        self._after_physics()
        self._steps += 1

        x_after, y = qpos[self._pelvis_x_adr], qpos[self._pelvis_y_adr]
        reward = (x_after - x_before) - math.sqrt(sum(f * f for f in forces)) * LIGAMENT_PENALTY
        terminated = y < FALL_HEIGHT
        truncated = self._steps >= self.max_steps
        if terminated or truncated:
            self._step_impl = _require_reset
        obs = self._observe()
        return obs.copy(), reward, terminated, truncated, self._info()

    def _after_physics(self) -> None:
        """What the observation needs beyond mj_step1: the centre of mass velocity."""
        mujoco.mj_subtreeVel(self._m, self._d)

    def _record_contacts(self) -> None:
        """World-frame force on each foot sphere from the last substep's contacts."""
        d = self._d
        out = self._contact_force
        out[:] = 0.0
        if d.ncon == 0:
            return
        con = d.contact
        slots = self._foot_slot[con.geom]  # (ncon, 2)
        for col, sign in ((0, -1.0), (1, 1.0)):  # the force acts on geom2 along the normal
            rows = np.flatnonzero(slots[:, col] >= 0)
            for r in rows:
                f6 = np.zeros(6)
                mujoco.mj_contactForce(self._m, d, int(r), f6)
                frame = con.frame[r].reshape(3, 3)
                out[slots[r, col]] += sign * (f6[:3] @ frame)

    # ------------------------------------------------------------------------- observation, info

    def _observe(self) -> np.ndarray:
        d, state = self._d, self._state
        nq, nv = self._m.nq, self._m.nv
        state[:nq] = d.qpos
        state[nq : nq + nv] = d.qvel
        state[nq + nv : nq + nv + 3] = d.subtree_com[0]
        state[nq + nv + 3 : nq + nv + 6] = d.subtree_linvel[0]
        state[nq + nv + 6 :] = d.xpos.reshape(-1)
        obs = self._obs
        obs[:36] = state[self._obs_gather]
        obs[OBS_PSOAS] = self.psoas
        obs[OBS_OBSTACLE] = next_obstacle(self.obstacles, float(d.qpos[self._pelvis_x_adr]))
        return obs

    def _info(self) -> dict[str, Any]:
        d = self._d
        return {
            "distance": float(d.qpos[self._pelvis_x_adr]),
            "body_pos": d.xpos.copy(),
            "body_quat": d.xquat.copy(),
            "muscle_activation": d.act[self._act_adr],
            "muscle_length": d.actuator_length.copy(),
            "muscle_force": -d.actuator_force,
            "ligament_force": np.array(self._lig_force),
            "contact_force": self._contact_force.copy(),
        }


def draw_episode(rng: np.random.Generator, difficulty: int):
    """Obstacles [(x, y, r)] sorted by x, and psoas strengths (left, right), as in 2017.

    x ~ U(1, 5) m; r = 0.05 + Exp(0.05) m; y = U(-0.25, 0.25) · r; strength = max(0.5, 1 - N(0, 0.1)).
    """
    obstacles: list[tuple[float, float, float]] = []
    if difficulty >= 1:
        xs = rng.uniform(1.0, 5.0, NUM_OBSTACLES)
        ys = rng.uniform(-0.25, 0.25, NUM_OBSTACLES)
        rs = 0.05 + rng.exponential(0.05, NUM_OBSTACLES)
        obstacles = sorted(zip(xs.tolist(), (ys * rs).tolist(), rs.tolist()))
    left = right = 1.0
    if difficulty >= 2:
        right = max(0.5, 1.0 - rng.normal(0.0, 0.1))
        left = max(0.5, 1.0 - rng.normal(0.0, 0.1))
    return obstacles, (left, right)


def next_obstacle(obstacles: list[tuple[float, float, float]], pelvis_x: float) -> tuple[float, float, float]:
    """The first obstacle whose far edge is not behind the pelvis: (x - pelvis x, y, r)."""
    for x, y, r in obstacles:
        if x + r >= pelvis_x:
            return (x - pelvis_x, y, r)
    return NO_OBSTACLE
