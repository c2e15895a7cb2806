"""`RunEnv`: the NeurIPS 2017 Learning to Run environment on the MuJoCo body.

One step is 0.01 s of simulated time: the 18 excitations are held while MuJoCo takes the
physics substeps, and the six joint-limit ligaments (`ligaments.py`) are recomputed from the
state before every substep, as OpenSim evaluates its `CoordinateLimitForce`s inside its
integrator: their springs as generalised forces, their damping as joint damping, which MuJoCo's
implicit integrator keeps stable. The observation, reward, done rules and episode generation follow the 2017
`RunEnv`; docs/environment.md has the observation table and the choices made.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np

from l2r.sim import model as body
from l2r.sim.ligaments import LIGAMENTS, LigamentKernel, default_limits

log = logging.getLogger(__name__)

STEP_SECONDS = 0.01
MAX_STEPS = 1000
FALL_HEIGHT = 0.65  # m; the episode ends when the pelvis drops below this
LIGAMENT_PENALTY = 1e-7  # reward per N·m of the ligament forces' Euclidean norm
NUM_OBSTACLES = 3
NO_OBSTACLE = (100.0, 0.0, 0.0)  # what the 2017 env reports when no obstacle lies ahead

PELVIS = ("pelvis_tilt", "pelvis_tx", "pelvis_ty")
JOINTS = ("hip_flexion_r", "knee_angle_r", "ankle_angle_r", "hip_flexion_l", "knee_angle_l", "ankle_angle_l")
TRACKED_BODIES = ("head", "pelvis", "torso", "toes_l", "toes_r", "talus_l", "talus_r")
FOOT_SPHERES = ("r_heel", "r_toe", "l_heel", "l_toe")
PSOAS_RIGHT = "iliopsoas_r"
# The 2017 code scaled muscle index 11 with the left psoas strength: glut_max_l, not iliopsoas_l.
LEFT_PSOAS_CHOICES = ("glut_max_l", "iliopsoas_l")

OBS_SIZE = 41
NET_FORCE = 3  # MuJoCo's contact-sensor reduction "netforce" (no Python enum for it)
NUM_MUSCLES = 18

# Warnings MuJoCo counts when it resets a diverging simulation.
DIVERGENCE_WARNINGS = tuple(
    int(getattr(mujoco.mjtWarning, f"mjWARN_BAD{what}")) for what in ("QACC", "QPOS", "QVEL")
)

Obstacle = tuple[float, float, float]  # (x, y, radius) in m

# MuJoCo's own warnings go to the log, not to a MUJOCO_LOG.TXT in whatever directory the
# process runs in (an actor would grow one without bound).
mujoco.set_mju_user_warning(lambda message: log.warning("MuJoCo: %s", message))


class RunEnv(gym.Env):
    """Run as far as possible in 1000 steps of 0.01 s by exciting 18 muscles.

    difficulty: 0 flat ground; 1 three sphere obstacles; 2 obstacles and random psoas strengths.
    seed: seeds the first `reset()` when that call passes none.
    left_psoas: the muscle the left psoas strength scales at difficulty 2: "glut_max_l" (what
        the 2017 code did, the default, so results compare with 2017) or "iliopsoas_l".
    max_steps: the episode is truncated after this many steps (1000 in 2017).
    """

    metadata = {"render_modes": []}

    def __init__(
        self,
        difficulty: int = 0,
        seed: int | None = None,
        left_psoas: str = "glut_max_l",
        max_steps: int = MAX_STEPS,
    ):
        _check_difficulty(difficulty)
        if left_psoas not in LEFT_PSOAS_CHOICES:
            raise ValueError(f"left_psoas must be one of {LEFT_PSOAS_CHOICES}, got {left_psoas!r}")
        if max_steps < 1:
            raise ValueError(f"max_steps must be at least 1, got {max_steps}")
        self.difficulty = difficulty
        self.left_psoas = left_psoas
        self.max_steps = max_steps
        self._seed = seed

        m = with_sensors(mujoco.MjSpec.from_file(str(body.MODEL_PATH)))
        d = mujoco.MjData(m)
        self._m, self._d = m, d
        self.substeps = round(STEP_SECONDS / m.opt.timestep)
        if self.substeps < 1 or abs(self.substeps * m.opt.timestep - STEP_SECONDS) > 1e-12:
            raise ValueError(f"the model's timestep {m.opt.timestep} s does not divide {STEP_SECONDS} s")

        # Everything the step needs is located once, by name, here.
        x_joint, y_joint = (_id(m, mujoco.mjtObj.mjOBJ_JOINT, c) for c in PELVIS[1:])
        self._x_adr, self._y_adr = int(m.jnt_qposadr[x_joint]), int(m.jnt_qposadr[y_joint])

        lig = default_limits()
        lig_joints = [_id(m, mujoco.mjtObj.mjOBJ_JOINT, c) for c in lig.coordinates]
        self.ligament_names = LIGAMENTS
        self._lig_kernel = LigamentKernel(m.jnt_qposadr[lig_joints], m.jnt_dofadr[lig_joints], lig)
        self._lig_dofs = m.jnt_dofadr[lig_joints].tolist()
        self._default_pose = m.keyframe(body.DEFAULT_KEYFRAME).id

        self.muscle_names = tuple(body.MUSCLES)
        muscles = [_id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, n) for n in self.muscle_names]
        if len(muscles) != NUM_MUSCLES or muscles != list(range(m.nu)):
            raise ValueError(f"the model's actuators must be the {NUM_MUSCLES} muscles, in action order")
        adr = m.actuator_actadr
        contiguous = np.array_equal(adr, np.arange(adr[0], adr[0] + NUM_MUSCLES))
        self._act = slice(int(adr[0]), int(adr[0]) + NUM_MUSCLES) if contiguous else adr.copy()
        self._psoas = (self.muscle_names.index(left_psoas), self.muscle_names.index(PSOAS_RIGHT))
        self._max_force = m.actuator_gainprm[:, 2].copy()

        # Observation values 0..35, and the foot contact forces, are gathers from the sensors
        # `with_sensors` added.
        def sensor(name: str, size: int) -> np.ndarray:
            adr = m.sensor_adr[_id(m, mujoco.mjtObj.mjOBJ_SENSOR, name)]
            return np.arange(adr, adr + size)

        pos = [sensor(f"l2r_q_{c}", 1) for c in PELVIS + JOINTS]
        vel = [sensor(f"l2r_qdot_{c}", 1) for c in PELVIS + JOINTS]
        self._obs_gather = np.concatenate(
            pos[:3] + vel[:3] + pos[3:] + vel[3:] + [sensor("l2r_com", 2), sensor("l2r_com_vel", 2)]
            + [sensor(f"l2r_pos_{b}", 2) for b in TRACKED_BODIES]
        )
        self._contact = np.concatenate([sensor(f"l2r_contact_{g}", 3) for g in FOOT_SPHERES])
        self.body_names = tuple(m.body(i).name for i in range(m.nbody))

        # Obstacles: three spheres of the world body, parked where the model put them when unused.
        self._obstacle_geoms = [
            _id(m, mujoco.mjtObj.mjOBJ_GEOM, f"obstacle_{i}") for i in range(NUM_OBSTACLES)
        ]
        self._parked = [(m.geom_pos[g].copy(), float(m.geom_size[g, 0])) for g in self._obstacle_geoms]

        self.action_space = gym.spaces.Box(0.0, 1.0, shape=(NUM_MUSCLES,), dtype=np.float32)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(OBS_SIZE,), dtype=np.float32)

        self.obstacles: list[Obstacle] = []  # this episode's, sorted by x
        self.psoas = (1.0, 1.0)  # this episode's strengths (left, right), as observed
        self._clipped = np.empty(NUM_MUSCLES)
        self._step_time = STEP_SECONDS - 0.5 * m.opt.timestep  # less time than this: MuJoCo reset
        self._steps = 0
        self._x = 0.0  # pelvis x
        self._lig_force: list[float] = []  # the ligament forces of the current state
        self._lig_applied: tuple[list[float], list[float]] = ([], [])  # (springs, dampings) in effect
        self._running = False

    # Read-only views for the validator and loggers; the env alone changes the simulation.
    @property
    def model(self) -> mujoco.MjModel:
        return self._m

    @property
    def data(self) -> mujoco.MjData:
        return self._d

    def reset(
        self, *, seed: int | None = None, options: dict | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode from the default pose with a new obstacle course and psoas strengths.

        options: {"difficulty": 0|1|2} changes the difficulty from this episode on.
        """
        if seed is None:
            seed, self._seed = self._seed, None
        super().reset(seed=seed)
        if options and "difficulty" in options:
            _check_difficulty(options["difficulty"])
            self.difficulty = options["difficulty"]
        m, d = self._m, self._d

        self.obstacles, self.psoas = draw_episode(self.np_random, self.difficulty)
        for i, g in enumerate(self._obstacle_geoms):
            if i < len(self.obstacles):
                x, y, r = self.obstacles[i]
                pos = (x, y, 0.0)
            else:
                pos, r = self._parked[i]
            m.geom_pos[g] = pos
            m.geom_size[g, 0] = r
            m.geom_rbound[g] = r
            m.geom_aabb[g, 3:] = r  # the broad phase reads the box, not only rbound
        force = self._max_force.copy()
        force[list(self._psoas)] *= self.psoas
        m.actuator_gainprm[:, 2] = force
        m.actuator_biasprm[:, 2] = force

        # The .osim default pose, at rest; its ligaments are set before the one forward pass,
        # so the passive forces include their damping.
        mujoco.mj_resetDataKeyframe(m, d, self._default_pose)
        self._lig_applied = ([], [])  # the reset cleared qfrc_applied: write both again
        self._apply_ligaments(self._lig_kernel(d.qpos.tolist()))
        mujoco.mj_forward(m, d)
        self._lig_force = self._lig_kernel.total(*self._lig_applied, d.qvel.tolist())
        self._x = float(d.qpos[self._x_adr])
        self._steps = 0
        self._running = True
        return self._observe(), self._info()

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Advance 0.01 s. Excitations outside [0, 1] are clipped to it; NaN, inf or a shape
        other than (18,) raise ValueError."""
        if not self._running:
            raise RuntimeError("RunEnv.step() needs reset() first, and again after an episode ends")
        a = np.asarray(action, dtype=np.float64)
        if a.shape != (NUM_MUSCLES,):
            raise ValueError(
                f"action must have shape ({NUM_MUSCLES},), one excitation per muscle; got {a.shape}"
            )
        # The sum is finite for every sane action; only otherwise is the element-wise test needed.
        if not math.isfinite(a.sum()) and not np.isfinite(a).all():
            raise ValueError(f"action contains NaN or inf: {a.tolist()}")
        m, d = self._m, self._d
        np.minimum(np.maximum(a, 0.0, out=self._clipped), 1.0, out=d.ctrl)

        # Substeps as step2 then step1, so that after the loop the kinematics (body positions,
        # centre of mass, tendon lengths) describe the final state without an extra mj_forward.
        # The ligaments depend on positions alone, so they are set between the two halves, after
        # the integration moved the joints and before step1 computes the passive (damping) forces.
        t_before = d.time
        kernel = self._lig_kernel
        for _ in range(self.substeps):
            mujoco.mj_step2(m, d)
            qpos = d.qpos.tolist()
            self._apply_ligaments(kernel(qpos))
            mujoco.mj_step1(m, d)
        forces = self._lig_force = kernel.total(*self._lig_applied, d.qvel.tolist())
        self._steps += 1

        x_before, self._x = self._x, qpos[self._x_adr]
        reward = (self._x - x_before) - math.sqrt(sum([f * f for f in forces])) * LIGAMENT_PENALTY
        terminated = qpos[self._y_adr] < FALL_HEIGHT
        truncated = self._steps >= self.max_steps
        info = self._info()
        # MuJoCo resets the data when the simulation diverges (time restarts, the body jumps to
        # its reference pose, a warning is counted): end the episode and say so.
        if (terminated or d.time < t_before + self._step_time) and self._diverged():
            log.warning("simulation diverged at step %d; episode terminated", self._steps)
            terminated, reward, info["diverged"] = True, 0.0, True
        self._running = not (terminated or truncated)
        return self._observe(), reward, terminated, truncated, info

    def _apply_ligaments(self, state: tuple[list[float], list[float]]) -> None:
        """Put the ligaments' springs in qfrc_applied and their damping in dof_damping (the body
        has no other joint damping); skipped when nothing changed, as within every limit."""
        if state == self._lig_applied:
            return
        qfrc, damping = self._d.qfrc_applied, self._m.dof_damping
        for dof, f, c in zip(self._lig_dofs, *state):
            qfrc[dof] = f
            damping[dof] = c
        self._lig_applied = state

    def _diverged(self) -> bool:
        """Whether MuJoCo has reset a diverging simulation since the episode began."""
        return any(self._d.warning[w].number for w in DIVERGENCE_WARNINGS)

    def _observe(self) -> np.ndarray:
        obs = np.empty(OBS_SIZE, dtype=np.float32)
        obs[:36] = self._d.sensordata[self._obs_gather]
        obs[36:] = (*self.psoas, *next_obstacle(self.obstacles, self._x))
        return obs

    def _info(self) -> dict[str, Any]:
        d = self._d
        return {
            "distance": self._x,
            "body_pos": d.xpos.copy(),
            "body_quat": d.xquat.copy(),
            "muscle_activation": d.act[self._act].copy(),
            "muscle_length": d.actuator_length.copy(),
            "muscle_force": -d.actuator_force,
            "ligament_force": np.array(self._lig_force),
            # The sensors report the force the sphere exerts; the force on it is the opposite.
            "contact_force": -d.sensordata[self._contact].reshape(len(FOOT_SPHERES), 3),
        }


def with_sensors(spec: mujoco.MjSpec) -> mujoco.MjModel:
    """Compile the body with the sensors the env reads: the observed coordinates and speeds,
    centre of mass position and velocity, tracked body positions, and the net contact force
    on each foot sphere. MuJoCo computes them inside the step, so the env only gathers."""
    sensor, obj = mujoco.mjtSensor, mujoco.mjtObj

    def add(name: str, kind: mujoco.mjtSensor, objtype: mujoco.mjtObj, objname: str) -> mujoco.MjsSensor:
        s = spec.add_sensor()
        s.name, s.type, s.objtype, s.objname = name, kind, objtype, objname
        return s

    for c in PELVIS + JOINTS:
        add(f"l2r_q_{c}", sensor.mjSENS_JOINTPOS, obj.mjOBJ_JOINT, c)
        add(f"l2r_qdot_{c}", sensor.mjSENS_JOINTVEL, obj.mjOBJ_JOINT, c)
    add("l2r_com", sensor.mjSENS_SUBTREECOM, obj.mjOBJ_BODY, "world")
    add("l2r_com_vel", sensor.mjSENS_SUBTREELINVEL, obj.mjOBJ_BODY, "world")
    for b in TRACKED_BODIES:
        add(f"l2r_pos_{b}", sensor.mjSENS_FRAMEPOS, obj.mjOBJ_XBODY, b)  # the body frame's origin
    force = 1 << int(mujoco.mjtConDataField.mjCONDATA_FORCE)
    for g in FOOT_SPHERES:
        # intprm: data fields, reduction (3 = net force of all the geom's contacts, world frame), count
        add(f"l2r_contact_{g}", sensor.mjSENS_CONTACT, obj.mjOBJ_GEOM, g).intprm[:3] = [force, NET_FORCE, 1]
    return spec.compile()


def draw_episode(rng: np.random.Generator, difficulty: int) -> tuple[list[Obstacle], tuple[float, float]]:
    """Obstacles sorted by x and psoas strengths (left, right), drawn as the 2017 env did.

    x ~ U(1, 5) m; r = 0.05 + Exp(mean 0.05) m; y = U(-0.25, 0.25) · r;
    strength = max(0.5, 1 - N(0, 0.1)), right then left.
    """
    obstacles: list[Obstacle] = []
    if difficulty >= 1:
        xs = rng.uniform(1.0, 5.0, NUM_OBSTACLES)
        ys = rng.uniform(-0.25, 0.25, NUM_OBSTACLES)
        rs = 0.05 + rng.exponential(0.05, NUM_OBSTACLES)
        obstacles = sorted(zip(xs.tolist(), (ys * rs).tolist(), rs.tolist()))
    left = right = 1.0
    if difficulty >= 2:
        right = max(0.5, 1.0 - float(rng.normal(0.0, 0.1)))
        left = max(0.5, 1.0 - float(rng.normal(0.0, 0.1)))
    return obstacles, (left, right)


def next_obstacle(obstacles: list[Obstacle], pelvis_x: float) -> Obstacle:
    """The first obstacle whose far edge is not behind the pelvis, as (x - pelvis x, y, r)."""
    for x, y, r in obstacles:
        if x + r >= pelvis_x:
            return (x - pelvis_x, y, r)
    return NO_OBSTACLE


def _check_difficulty(difficulty: Any) -> None:
    if difficulty not in (0, 1, 2):
        raise ValueError(f"difficulty must be 0, 1 or 2, got {difficulty!r}")


def _id(m: mujoco.MjModel, kind: mujoco.mjtObj, name: str) -> int:
    i = mujoco.mj_name2id(m, kind, name)
    if i < 0:
        raise ValueError(f"the body model has no {kind.name[6:].lower()} named {name!r}")
    return i
