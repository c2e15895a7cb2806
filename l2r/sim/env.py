"""`RunEnv`: the NeurIPS 2017 Learning to Run environment on the MuJoCo body.

One step is 0.01 s of simulated time: the 18 excitations are held while MuJoCo takes the
physics substeps, with OpenSim's muscle, contact, path and ligament dynamics computed around
each (`physics.py`, one kernel call per step). The observation, reward, done rules and episode
generation follow the 2017 `RunEnv`; docs/environment.md has the observation table and the
choices made.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np

from l2r.sim import model as body
from l2r.sim import thelen
from l2r.sim.contact import contact_law
from l2r.sim.layout import JOINTS, OBS_SIZE, PELVIS, TRACKED_BODIES
from l2r.sim.ligaments import LIGAMENTS
from l2r.sim.opensim import read_osim
from l2r.sim.physics import Physics
from l2r.sim.randomize import CONTACT_FIELDS, MUSCLE_FIELDS, Randomization

log = logging.getLogger(__name__)

STEP_SECONDS = 0.01
MAX_STEPS = 1000
FALL_HEIGHT = 0.65  # m; the episode ends when the pelvis drops below this
LIGAMENT_PENALTY = 1e-7  # reward per N·m of the ligament forces' Euclidean norm
NUM_OBSTACLES = 3
NO_OBSTACLE = (100.0, 0.0, 0.0)  # what the 2017 env reports when no obstacle lies ahead

FOOT_SPHERES = body.CONTACT_SPHERES  # the rows of info["contact_force"]
PSOAS_RIGHT = "iliopsoas_r"
# The 2017 code scaled muscle index 11 with the left psoas strength: glut_max_l, not iliopsoas_l.
LEFT_PSOAS_CHOICES = ("glut_max_l", "iliopsoas_l")

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
    randomize: per-episode randomisation of the body (`Randomization`, or a mapping of its field
        names to fractions, such as {"strength": 0.05, "delay": 0.5}); None or all zero: off,
        the env of 2017.
    """

    metadata = {"render_modes": []}

    def __init__(
        self,
        difficulty: int = 0,
        seed: int | None = None,
        left_psoas: str = "glut_max_l",
        max_steps: int = MAX_STEPS,
        randomize: Randomization | Mapping[str, float] | None = None,
    ):
        check_arguments(difficulty, left_psoas, max_steps)
        self.randomize = Randomization.of(randomize)
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
        # MjData's arrays the step reads: the bindings make a new array object on every access
        self._qpos, self._sensordata, self._xpos, self._xquat = d.qpos, d.sensordata, d.xpos, d.xquat
        self.ligament_names = LIGAMENTS
        self._default_pose = m.keyframe(body.DEFAULT_KEYFRAME).id

        self.muscle_names = tuple(body.MUSCLES)
        actuators = [_id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, n) for n in self.muscle_names]
        if actuators != list(range(NUM_MUSCLES)):
            raise ValueError(f"the model's first actuators must be the {NUM_MUSCLES} muscles, in action order")
        self._psoas = (self.muscle_names.index(left_psoas), self.muscle_names.index(PSOAS_RIGHT))
        osim = read_osim(body.OSIM_PATH)
        by_name = {mu.name: mu for mu in osim.muscles}
        self._physics = Physics(m, d, osim, [by_name[n] for n in self.muscle_names])
        self._muscle_table = self._physics.params.copy()  # before this episode's psoas strengths
        # The body as the model has it, which randomisation scales per episode. MuJoCo's
        # invweight0 constants, which scale the constraints' softness, keep the default masses'.
        self._contact_law = contact_law(osim)
        self._segment_mass, self._segment_inertia = m.body_mass[1:].copy(), m.body_inertia[1:].copy()

        # Observation values 0..35 are a gather from the sensors `with_sensors` added.
        self._obs_gather = sensor_gathers(m)
        self.body_names = tuple(m.body(i).name for i in range(m.nbody))

        # Obstacles: three spheres of the world body for the renderer, parked where the model put
        # them when unused; the physics pushes the feet off this episode's `course`.
        self._obstacle_geoms = [
            _id(m, mujoco.mjtObj.mjOBJ_GEOM, f"obstacle_{i}") for i in range(NUM_OBSTACLES)
        ]
        self._parked = [(m.geom_pos[g].copy(), float(m.geom_size[g, 0])) for g in self._obstacle_geoms]

        self.action_space = gym.spaces.Box(0.0, 1.0, shape=(NUM_MUSCLES,), dtype=np.float32)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(OBS_SIZE,), dtype=np.float32)

        self.obstacles: list[Obstacle] = []  # this episode's, sorted by x
        self.psoas = (1.0, 1.0)  # this episode's strengths (left, right), as observed
        self.randomized: dict[str, Any] = {}  # this episode's randomisation draws (`Randomization.draw`)
        self._delayed = False  # whether this episode's excitations act one physics step late
        self._step_time = STEP_SECONDS - 0.5 * m.opt.timestep  # less time than this: MuJoCo reset
        self._steps = 0
        self._x = 0.0  # pelvis x
        self._running = False

    # Read-only views for the validator and loggers; the env alone changes the simulation.
    @property
    def model(self) -> mujoco.MjModel:
        return self._m

    @property
    def data(self) -> mujoco.MjData:
        return self._d

    @property
    def max_isometric_force(self) -> np.ndarray:
        """This episode's max isometric forces (N), psoas strengths applied, in action order."""
        return self._physics.params[:, thelen.MAX_FORCE].copy()

    @property
    def excitation(self) -> np.ndarray:
        """The excitations held over the last step, clipped to [0, 1]."""
        return self._physics.excitation.copy()

    def reset(
        self, *, seed: int | None = None, options: dict | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode from the default pose with a new obstacle course and psoas strengths
        (and, when `randomize` is on, a new body: its draws are info["randomization"]).

        options: {"difficulty": 0|1|2} changes the difficulty from this episode on.
        """
        start_episode(self, seed, options)
        m, d = self._m, self._d
        course = self._physics.course
        course[:] = 0.0
        for i, g in enumerate(self._obstacle_geoms):
            if i < len(self.obstacles):
                x, y, r = self.obstacles[i]
                pos = (x, y, 0.0)
                course[i] = self.obstacles[i]
            else:
                pos, r = self._parked[i]
            m.geom_pos[g] = pos
            m.geom_size[g, 0] = r
            m.geom_rbound[g] = r  # MuJoCo's bound of the geom, kept with its size
        params = self._physics.params
        params[:] = self._muscle_table
        params[list(self._psoas), thelen.MAX_FORCE] *= self.psoas
        if self.randomize:
            self.randomized = self.randomize.draw(self.np_random, NUM_MUSCLES, m.nbody - 1)
            self._randomize_body(self.randomized)

        # The .osim default pose, at rest, muscles as OpenSim starts them.
        mujoco.mj_resetDataKeyframe(m, d, self._default_pose)
        self._physics.reset()
        self._x = float(self._qpos[self._x_adr])
        self._steps = 0
        self._running = True
        info = self._info()
        if self.randomize:
            info["randomization"] = self.randomized
        return self._observe(), info

    def _randomize_body(self, drawn: dict[str, Any]) -> None:
        """This episode's body: the default one scaled by the drawn factors."""
        m = self._m
        thelen.scale_muscles(self._physics.params, **{name: drawn[name] for name in MUSCLE_FIELDS if name in drawn})
        if "mass" in drawn:
            m.body_mass[1:] = self._segment_mass * drawn["mass"]
            m.body_inertia[1:] = self._segment_inertia * drawn["mass"][:, None]
            # MuJoCo's centre of mass divides by them
            m.body_subtreemass[:] = subtree_masses(m.body_mass, m.body_parentid)
        if any(name in drawn for name in CONTACT_FIELDS):
            law = self._contact_law.scaled(*(drawn.get(name, 1.0) for name in CONTACT_FIELDS))
            self._physics.contact[:] = law.table()
        self._delayed = drawn.get("delay", False)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Advance 0.01 s. Excitations outside [0, 1] are clipped to it; NaN, inf or a shape
        other than (18,) raise ValueError."""
        if not self._running:
            raise RuntimeError("RunEnv.step() needs reset() first, and again after an episode ends")
        physics, d = self._physics, self._d
        t_before = d.time
        if self._delayed:  # the last step's excitations act for one more physics step
            checked_excitations(action, out=physics.next_excitation)
            physics.step(self.substeps, delay=1)
        else:
            checked_excitations(action, out=physics.excitation)
            physics.step(self.substeps)
        self._steps += 1

        qpos = self._qpos
        x_before, self._x = self._x, float(qpos[self._x_adr])
        forces = physics.ligament_force.tolist()
        reward = (self._x - x_before) - math.sqrt(sum([f * f for f in forces])) * LIGAMENT_PENALTY
        terminated = bool(qpos[self._y_adr] < FALL_HEIGHT)
        truncated = self._steps >= self.max_steps
        info = self._info()
        # MuJoCo resets the data when the simulation diverges (time restarts, the body jumps to
        # its reference pose, a warning is counted): end the episode and say so.
        if (terminated or d.time < t_before + self._step_time) and self._diverged():
            log.warning("simulation diverged at step %d; episode terminated", self._steps)
            terminated, reward, info["diverged"] = True, 0.0, True
        self._running = not (terminated or truncated)
        return self._observe(), reward, terminated, truncated, info

    def _diverged(self) -> bool:
        """Whether MuJoCo has reset a diverging simulation since the episode began."""
        return any(self._d.warning[w].number for w in DIVERGENCE_WARNINGS)

    def _observe(self) -> np.ndarray:
        obs = np.empty(OBS_SIZE, dtype=np.float32)
        obs[:36] = self._sensordata[self._obs_gather]
        obs[36:] = (*self.psoas, *next_obstacle(self.obstacles, self._x))
        return obs

    def _info(self) -> dict[str, Any]:
        physics = self._physics
        contact = physics.obstacle_force.copy()
        contact[:, :2] += physics.ground_force
        return {
            "distance": self._x,
            "body_pos": self._xpos.copy(),
            "body_quat": self._xquat.copy(),
            "muscle_activation": physics.activation.copy(),
            "muscle_length": physics.muscle_length.copy(),
            "muscle_force": physics.muscle_force.copy(),
            "fiber_length": physics.fiber.copy(),
            "ligament_force": physics.ligament_force.copy(),
            "contact_force": contact,
        }


def with_sensors(spec: mujoco.MjSpec) -> mujoco.MjModel:
    """Compile the body with the sensors the env reads: the observed coordinates and speeds,
    centre of mass position and velocity, tracked body positions. MuJoCo computes them inside
    the step, so the env only gathers."""
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
    return spec.compile()


def subtree_masses(body_mass: np.ndarray, body_parentid: np.ndarray) -> np.ndarray:
    """Each body's mass with its descendants' (MuJoCo's body_subtreemass) for these masses of a
    model's bodies."""
    mass = body_mass.copy()
    for b in range(len(mass) - 1, 0, -1):  # children come after their parents
        mass[body_parentid[b]] += mass[b]
    return mass


def sensor_gathers(m: mujoco.MjModel) -> np.ndarray:
    """Indices into sensordata of a model compiled by `with_sensors`: observation values 0..35."""
    def sensor(name: str, size: int) -> np.ndarray:
        adr = m.sensor_adr[_id(m, mujoco.mjtObj.mjOBJ_SENSOR, name)]
        return np.arange(adr, adr + size)

    pos = [sensor(f"l2r_q_{c}", 1) for c in PELVIS + JOINTS]
    vel = [sensor(f"l2r_qdot_{c}", 1) for c in PELVIS + JOINTS]
    return np.concatenate(
        pos[:3] + vel[:3] + pos[3:] + vel[3:] + [sensor("l2r_com", 2), sensor("l2r_com_vel", 2)]
        + [sensor(f"l2r_pos_{b}", 2) for b in TRACKED_BODIES]
    )


def check_arguments(difficulty: Any, left_psoas: Any, max_steps: Any) -> None:
    """ValueError, saying what is wrong, for constructor arguments no backend accepts."""
    check_difficulty(difficulty)
    if left_psoas not in LEFT_PSOAS_CHOICES:
        raise ValueError(f"left_psoas must be one of {LEFT_PSOAS_CHOICES}, got {left_psoas!r}")
    if max_steps < 1:
        raise ValueError(f"max_steps must be at least 1, got {max_steps}")


def checked_excitations(action: Any, out: np.ndarray | None = None) -> np.ndarray:
    """The action as 18 excitations clipped to [0, 1] (into `out` when given); ValueError for
    another shape, NaN or inf."""
    a = np.asarray(action, dtype=np.float64)
    if a.shape != (NUM_MUSCLES,):
        raise ValueError(f"action must have shape ({NUM_MUSCLES},), one excitation per muscle; got {a.shape}")
    # The sum is finite for every sane action; only otherwise is the element-wise test needed.
    if not math.isfinite(a.sum()) and not np.isfinite(a).all():
        raise ValueError(f"action contains NaN or inf: {a.tolist()}")
    return a.clip(0.0, 1.0, out=out)  # the method: half the cost of np.clip's dispatch


def start_episode(env: gym.Env, seed: int | None, options: dict | None) -> None:
    """What every backend's reset does first: seed the env's generator (with the constructor's
    seed when the first reset passes none), take a difficulty option, and draw the episode's
    obstacles and psoas strengths into `env.obstacles` and `env.psoas`."""
    if seed is None:
        seed, env._seed = env._seed, None
    gym.Env.reset(env, seed=seed)
    if options and "difficulty" in options:
        check_difficulty(options["difficulty"])
        env.difficulty = options["difficulty"]
    env.obstacles, env.psoas = draw_episode(env.np_random, env.difficulty)


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


def check_difficulty(difficulty: Any) -> None:
    """ValueError for a difficulty other than 0, 1 or 2."""
    if difficulty not in (0, 1, 2):
        raise ValueError(f"difficulty must be 0, 1 or 2, got {difficulty!r}")


def _id(m: mujoco.MjModel, kind: mujoco.mjtObj, name: str) -> int:
    i = mujoco.mj_name2id(m, kind, name)
    if i < 0:
        raise ValueError(f"the body model has no {kind.name[6:].lower()} named {name!r}")
    return i
