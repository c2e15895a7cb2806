"""`RunOpenSimEnv`: the Learning to Run environment on OpenSim 4.6 itself, the simulator of 2017.

The same gymnasium API, observation, reward, done rules and episode draws as `RunEnv`
(`l2r.sim.env`), computed by OpenSim on the packaged .osim model: a reset puts the body in the
model's default pose with every muscle at activation 0.05 and its fibre in equilibrium; a step
holds the 18 excitations (a `PrescribedController` of `Constant`s) while OpenSim's Manager
integrates 0.01 s with the Runge-Kutta-Merson integrator at the given accuracy (5e-5 in 2017).

The Manager lives for the whole episode, so while the excitations are held the integrator
keeps its step size from one step to the next; that reproduces the zero-excitation reference
rollout of `assets/opensim_reference.json` bit for bit. When the excitations change, the
integrator is restarted from the current state, as a new Manager per step did in 2017: its step
history holds derivatives computed with the old excitations, and a step begun from them lags
the change (the reference's second rollout did; its first step is 50 times further from an
exact integration than the env's). With random excitations, restarting is also 20-40 % faster
than carrying on, and 4-6 times closer to an integration at accuracy 1e-9.

Obstacles are spheres fixed to the ground with their own Hunt-Crossley contact to the four foot
spheres, as in 2017: stiffness 1e6 / radius, dissipation 1e-5, no friction. Moving or resizing
a sphere changes the model, so a reset whose course differs from the last one rebuilds the
Simbody system (`initSystem`; see docs/environment.md for the cost). Unused spheres apply no
force.

OpenSim is an optional dependency (`pip install 'l2r[opensim]'`), imported when an env is made.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import gymnasium as gym
import numpy as np

from l2r.sim.env import (
    FALL_HEIGHT, FOOT_SPHERES, JOINTS, LIGAMENT_PENALTY, MAX_STEPS, NUM_MUSCLES,
    OBS_SIZE, PELVIS, PSOAS_RIGHT, STEP_SECONDS, TRACKED_BODIES, Obstacle, check_arguments,
    checked_excitations, next_obstacle, start_episode,
)  # fmt: skip
from l2r.sim.contact import OBSTACLE_DISSIPATION, OBSTACLE_STIFFNESS_TIMES_RADIUS
from l2r.sim.ligaments import LIGAMENTS
from l2r.sim.model import BODIES, MUSCLES, OBSTACLES, OSIM_PATH

log = logging.getLogger(__name__)

MISSING_OPENSIM = "l2r/RunOpenSim-v0 needs OpenSim 4.6: pip install 'l2r[opensim]' (or make setup)"
ACCURACY = 5e-5  # the 2017 env's integrator accuracy
INITIAL_ACTIVATION = 0.05  # OpenSim's default activation, every muscle's at reset
PARKED = (0.0, 0.0, 0.05)  # (x, y, r) of an unused obstacle sphere; it applies no force
WORLD = "world"  # MuJoCo's name for the ground; `body_names` follow the MuJoCo body's order


def load_opensim():
    """The opensim module, its log set to errors only (its warnings about this model, mesh files
    that are not shipped and an old file format, say nothing about the simulation); an
    ImportError that says how to install it when it is missing."""
    try:
        import opensim
    except ImportError as e:
        raise ImportError(MISSING_OPENSIM) from e
    if opensim.Logger.getLevel() < opensim.Logger.Level_Error:
        opensim.Logger.setLevel(opensim.Logger.Level_Error)
    return opensim


class RunOpenSimEnv(gym.Env):
    """Run as far as possible in 1000 steps of 0.01 s by exciting 18 muscles, in OpenSim.

    The arguments are `RunEnv`'s, plus accuracy: the integrator's (OpenSim's relative
    accuracy; 5e-5 as in 2017).
    """

    metadata = {"render_modes": []}

    def __init__(
        self,
        difficulty: int = 0,
        seed: int | None = None,
        left_psoas: str = "glut_max_l",
        max_steps: int = MAX_STEPS,
        accuracy: float = ACCURACY,
    ):
        check_arguments(difficulty, left_psoas, max_steps)
        if not 0 < accuracy < 1:
            raise ValueError(f"accuracy must be between 0 and 1, got {accuracy}")
        osim = self._osim = load_opensim()
        self.difficulty = difficulty
        self.left_psoas = left_psoas
        self.max_steps = max_steps
        self.accuracy = accuracy
        self._seed = seed
        self.muscle_names = tuple(MUSCLES)
        self.body_names = (WORLD,) + BODIES
        self.ligament_names = LIGAMENTS

        m = self._model = osim.Model(str(OSIM_PATH))
        # Excitations: one Constant per muscle, in action order, changed in place at each step.
        controller = self._controller = osim.PrescribedController()
        self._muscles = [osim.Thelen2003Muscle.safeDownCast(m.getMuscles().get(n)) for n in self.muscle_names]
        for muscle in self._muscles:
            controller.addActuator(muscle)
            controller.prescribeControlForActuator(muscle.getName(), osim.Constant(0.0))
        m.addController(controller)
        self._controls = []  # the Constants, found again after each build
        self._max_force = [muscle.getMaxIsometricForce() for muscle in self._muscles]
        self._psoas = (self.muscle_names.index(left_psoas), self.muscle_names.index(PSOAS_RIGHT))

        self._obstacle_spheres, self._obstacle_forces = [], []
        for name in OBSTACLES:
            sphere = osim.ContactSphere(PARKED[2], osim.Vec3(*PARKED[:2], 0.0), m.getGround(), name)
            m.addContactGeometry(sphere)
            force = osim.HuntCrossleyForce()
            force.setName(f"{name}_contact")
            for geometry in (name, *FOOT_SPHERES):
                force.addGeometry(geometry)
            force.setStiffness(OBSTACLE_STIFFNESS_TIMES_RADIUS / PARKED[2])
            force.setDissipation(OBSTACLE_DISSIPATION)
            force.setStaticFriction(0.0)
            force.setDynamicFriction(0.0)
            force.setViscousFriction(0.0)
            m.addForce(force)
            self._obstacle_spheres.append(sphere)
            self._obstacle_forces.append(force)
        self._built_course: list[Obstacle] = []
        self._build()

        coordinates = m.getCoordinateSet()
        self._pelvis = [coordinates.get(c) for c in PELVIS]
        self._joints = [coordinates.get(c) for c in JOINTS]
        self._bodies = [m.getBodySet().get(b) for b in BODIES]
        self._tracked = [self.body_names.index(b) for b in TRACKED_BODIES]
        forces = m.getForceSet()
        self._ligaments = [osim.CoordinateLimitForce.safeDownCast(forces.get(n)) for n in LIGAMENTS]
        # Foot contact: each Hunt-Crossley force records the force on each body its spheres are
        # on; each foot sphere is alone on its body, so a record is the force on that sphere.
        sphere_body = {
            g: m.getContactGeometrySet().get(g).getFrame().findBaseFrame().getName() for g in FOOT_SPHERES
        }
        contacts = [forces.get(n) for n in ("foot_r", "foot_l")] + self._obstacle_forces
        self._contacts = [(f, self._contact_records(f, sphere_body)) for f in contacts]  # ground, then obstacles

        self.action_space = gym.spaces.Box(0.0, 1.0, shape=(NUM_MUSCLES,), dtype=np.float32)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(OBS_SIZE,), dtype=np.float32)

        self.obstacles: list[Obstacle] = []  # this episode's, sorted by x
        self.psoas = (1.0, 1.0)  # this episode's strengths (left, right), as observed
        self._manager = None
        self._state = None
        self._excitations = np.zeros(NUM_MUSCLES)  # the Constants' values
        self._steps = 0
        self._x = 0.0  # pelvis x
        self._last: tuple[np.ndarray, dict[str, Any]] | None = None  # observation and info of the state
        self._running = False

    # Read-only views for tests and tools; the env alone changes the simulation.
    @property
    def osim_model(self):
        return self._model

    @property
    def state(self):
        return self._state

    def reset(
        self, *, seed: int | None = None, options: dict | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode from the default pose with a new obstacle course and psoas strengths.

        options: {"difficulty": 0|1|2} changes the difficulty from this episode on.
        """
        start_episode(self, seed, options)
        osim, m = self._osim, self._model
        strengths = [1.0] * NUM_MUSCLES
        for muscle, strength in zip(self._psoas, self.psoas):
            strengths[muscle] = strength
        for muscle, force, strength in zip(self._muscles, self._max_force, strengths):
            muscle.setMaxIsometricForce(force * strength)
        if self.obstacles != self._built_course:
            self._build_course(self.obstacles)

        state = m.initializeState()
        for i, force in enumerate(self._obstacle_forces):
            force.setAppliesForce(state, i < len(self.obstacles))
        for muscle in self._muscles:
            muscle.setActivation(state, INITIAL_ACTIVATION)
        m.equilibrateMuscles(state)
        state.setTime(0.0)
        self._set_excitations(np.zeros(NUM_MUSCLES))
        manager = self._manager = osim.Manager(m)
        manager.setIntegratorMethod(osim.Manager.IntegratorMethod_RungeKuttaMerson)
        manager.setIntegratorAccuracy(self.accuracy)
        manager.initialize(state)
        self._state = manager.getState()
        self._steps = 0
        self._x = self._pelvis[1].getValue(self._state)
        self._running = True
        self._last = self._observe()
        return self._last

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Advance 0.01 s. Excitations outside [0, 1] are clipped to it; NaN, inf or a shape
        other than (18,) raise ValueError."""
        if not self._running:
            raise RuntimeError("RunOpenSimEnv.step() needs reset() first, and again after an episode ends")
        excitations = checked_excitations(action)
        if not np.array_equal(excitations, self._excitations):
            self._set_excitations(excitations)
            self._manager.initialize(self._osim.State(self._state))
        self._steps += 1
        try:
            self._state = self._manager.integrate(self._steps * STEP_SECONDS)
            obs, info = self._observe()
        except RuntimeError as e:  # OpenSim gave up on the step (an integrator failure)
            obs, info = self._diverged(str(e).splitlines()[-1])
        else:
            if not np.isfinite(obs).all():
                obs, info = self._diverged("non-finite state")
        if "diverged" in info:
            self._running = False
            return obs, 0.0, True, False, info
        self._last = obs, info
        x_before, self._x = self._x, info["distance"]
        forces = info["ligament_force"]
        reward = (self._x - x_before) - math.sqrt(float(forces @ forces)) * LIGAMENT_PENALTY
        terminated = self._pelvis[2].getValue(self._state) < FALL_HEIGHT
        truncated = self._steps >= self.max_steps
        self._running = not (terminated or truncated)
        return obs, reward, terminated, truncated, info

    def _diverged(self, why: str) -> tuple[np.ndarray, dict[str, Any]]:
        """The last good observation and info, marked diverged: the episode ends there."""
        log.warning("OpenSim simulation failed at step %d (%s); episode terminated", self._steps, why)
        obs, info = self._last
        copied = {k: v.copy() if isinstance(v, np.ndarray) else v for k, v in info.items()}
        return obs.copy(), {**copied, "diverged": True}

    def _set_excitations(self, excitations: np.ndarray) -> None:
        for constant, value in zip(self._controls, excitations.tolist()):
            constant.setValue(value)
        self._excitations = excitations

    def _build_course(self, obstacles: list[Obstacle]) -> None:
        """Move and size the obstacle spheres and rebuild the system (positions and radii are
        model properties, read when Simbody's contact geometry is made)."""
        osim = self._osim
        for i, (sphere, force) in enumerate(zip(self._obstacle_spheres, self._obstacle_forces)):
            x, y, r = obstacles[i] if i < len(obstacles) else PARKED
            sphere.set_location(osim.Vec3(x, y, 0.0))
            sphere.setRadius(r)
            force.setStiffness(OBSTACLE_STIFFNESS_TIMES_RADIUS / r)
        self._build()
        self._built_course = list(obstacles)

    def _build(self) -> None:
        """Build the Simbody system; the controller's functions are made anew with it."""
        self._model.initSystem()
        functions = self._controller.get_ControlFunctions()
        self._controls = [self._osim.Constant.safeDownCast(functions.get(i)) for i in range(NUM_MUSCLES)]

    def _contact_records(self, force, sphere_body: dict[str, str]) -> list[int | None]:
        """For each foot sphere, where the force's record of the force on its body starts (or
        None when the force does not touch that sphere)."""
        records = force.getRecordLabels()
        labels = [records.get(i) for i in range(records.size())]
        starts = []
        for sphere in FOOT_SPHERES:
            label = f"{force.getName()}.{sphere_body[sphere]}.force.X"
            starts.append(labels.index(label) if label in labels else None)
        return starts

    def _observe(self) -> tuple[np.ndarray, dict[str, Any]]:
        """The observation and the info of the current state."""
        m, s = self._model, self._state
        m.realizeDynamics(s)  # muscle forces and contact records are Dynamics-stage values
        pos = np.zeros((len(self.body_names), 3))
        quat = np.zeros((len(self.body_names), 4))
        quat[0, 0] = 1.0
        for i, b in enumerate(self._bodies, start=1):
            frame = b.getTransformInGround(s)
            pos[i] = frame.p().to_numpy()
            q = frame.R().convertRotationToQuaternion()
            quat[i] = (q.get(0), q.get(1), q.get(2), q.get(3))
        com, com_vel = m.calcMassCenterPosition(s), m.calcMassCenterVelocity(s)
        x = self._pelvis[1].getValue(s)
        obs = np.array(
            [c.getValue(s) for c in self._pelvis] + [c.getSpeedValue(s) for c in self._pelvis]
            + [c.getValue(s) for c in self._joints] + [c.getSpeedValue(s) for c in self._joints]
            + [com.get(0), com.get(1), com_vel.get(0), com_vel.get(1)]
            + pos[self._tracked, :2].ravel().tolist() + list(self.psoas) + list(next_obstacle(self.obstacles, x)),
            dtype=np.float32,
        )  # fmt: skip
        info = {
            "distance": x,
            "body_pos": pos,
            "body_quat": quat,
            "muscle_activation": np.array([mu.getActivation(s) for mu in self._muscles]),
            "muscle_length": np.array([mu.getLength(s) for mu in self._muscles]),
            "muscle_force": np.array([mu.getTendonForce(s) for mu in self._muscles]),
            "fiber_length": np.array([mu.getFiberLength(s) for mu in self._muscles]),
            "ligament_force": np.array([lig.calcLimitForce(s) for lig in self._ligaments]),
            "contact_force": self._contact_force(),
        }
        return obs, info

    def _contact_force(self) -> np.ndarray:
        """World force (N) on each foot sphere from the ground and the obstacles in use."""
        total = np.zeros((len(FOOT_SPHERES), 3))
        for force, starts in self._contacts[: 2 + len(self.obstacles)]:
            values = force.getRecordValues(self._state)
            for sphere, start in enumerate(starts):
                if start is not None:
                    total[sphere] += (values.get(start), values.get(start + 1), values.get(start + 2))
        return total

