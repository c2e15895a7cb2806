"""`l2r.sim.physics` on MuJoCo Warp: the runner's force elements around its step, N worlds at once.

Every physics step runs as the numba backend's does (`physics._advance`), each part a Warp
launch over all worlds: the muscles, moving points and feet drive the actuators, MuJoCo Warp's
transmission and step2 integrate, the knee slides go back onto their splines, the ligaments,
moving points and knee couplings are placed for the new positions, and step1 computes the
kinematics the next step and the observation read. The arrays are float32 (MuJoCo Warp's), the
tables the numba modules build.

Per-world model fields that the kernels write (moving sites, actuator bias, ligament damping,
knee couplings, the obstacles' places and sizes) are batched in the MuJoCo Warp model
(`put_model`'s batch_sizes), and with `per_world_bodies` the segments' masses and inertias, which
a randomised env writes per episode.
"""

from __future__ import annotations

import logging

import mujoco
import mujoco_warp as mjw
import numpy as np
import warp as wp

from l2r.sim import model as body
from l2r.sim import thelen
from l2r.sim.contact import contact_elements, contact_law
from l2r.sim.knee import KneeCoupling
from l2r.sim.ligaments import default_limits, ligament_table
from l2r.sim.opensim import Muscle, Osim
from l2r.sim.paths import MovingPoints, PathSwitches
from l2r.sim.physics import FIBER_SUBSTEPS
from l2r.sim.warp import contact as feet
from l2r.sim.warp import knee as knees
from l2r.sim.warp import ligaments as limits
from l2r.sim.warp import paths as points
from l2r.sim.warp import thelen as muscles

wp.set_module_options({"enable_backward": False})
log = logging.getLogger(__name__)

# Model fields the kernels change per world: per physics step, and per episode (the obstacles,
# drawn where the physics pushes the feet off them).
PER_WORLD_FIELDS = ("site_pos", "actuator_biasprm", "dof_damping", "eq_data", "geom_pos", "geom_size")
BODY_FIELDS = ("body_mass", "body_inertia", "body_subtreemass")


def _ints(x) -> wp.array:
    return wp.array(np.asarray(x, np.int32), dtype=int)


def _floats(x, dtype=float) -> wp.array:
    return wp.array(np.asarray(x, np.float32), dtype=dtype)


@wp.struct
class Muscles:
    table: wp.array(dtype=muscles.MuscleRow)  # the muscles' parameters as the model has them
    strength: wp.array2d(dtype=float)  # per world and muscle: max isometric force over the table's
    fiber_scale: wp.array2d(dtype=float)  # per world and muscle: optimal fibre length over the table's
    slack_scale: wp.array2d(dtype=float)  # per world and muscle: tendon slack length over the table's
    params: wp.array2d(dtype=muscles.MuscleRow)  # per world: the table, the scales applied
    excitation: wp.array2d(dtype=float)  # what each physics step holds
    next_excitation: wp.array2d(dtype=float)  # what the env asked for this step
    delay: wp.array(dtype=int)  # per world: physics steps `excitation` holds before it turns to `next_excitation`
    activation: wp.array2d(dtype=float)
    fiber: wp.array2d(dtype=float)
    length: wp.array2d(dtype=float)
    force: wp.array2d(dtype=float)
    tendon: wp.array2d(dtype=int)  # the tendon each muscle pulls through now
    tension: wp.array2d(dtype=float)  # per tendon
    on: wp.array(dtype=int)
    switch_row: wp.array(dtype=int)
    switch_qpos: wp.array(dtype=int)
    low: wp.array(dtype=float)
    high: wp.array(dtype=float)
    off_tendon: wp.array(dtype=int)
    off_actuator: wp.array(dtype=int)


@wp.struct
class Moving:
    table: wp.array2d(dtype=wp.vec3)
    slope: wp.array2d(dtype=wp.vec3)
    qpos: wp.array(dtype=int)
    site: wp.array(dtype=int)
    neighbours: wp.array(dtype=wp.vec2i)
    body: wp.array(dtype=int)
    tendon: wp.array(dtype=int)
    dof: wp.array(dtype=int)
    actuator: wp.array(dtype=int)
    torque_actuators: wp.array(dtype=int)
    rate: wp.array2d(dtype=float)


@wp.struct
class Feet:
    law: wp.array2d(dtype=float)  # per world: `ContactLaw.table`
    radius: wp.array(dtype=float)
    sphere: wp.array(dtype=int)
    body: wp.array(dtype=int)
    root: wp.array(dtype=int)
    element: wp.array(dtype=int)  # each sphere's Hunt-Crossley force element (`contact.contact_elements`)
    site: wp.array(dtype=int)
    x_actuator: wp.array(dtype=int)
    y_actuator: wp.array(dtype=int)
    force: wp.array2d(dtype=wp.vec2)  # the ground's on each sphere
    obstacle_force: wp.array2d(dtype=wp.vec3)  # the obstacles' on each sphere


@wp.struct
class Ligaments:
    table: wp.array2d(dtype=float)
    qpos: wp.array(dtype=int)
    dof: wp.array(dtype=int)
    spring: wp.array2d(dtype=float)
    damping: wp.array2d(dtype=float)
    force: wp.array2d(dtype=float)


@wp.kernel
def _rates(mv: Moving, qpos: wp.array2d(dtype=float), site_xpos: wp.array2d(dtype=wp.vec3),
           xmat: wp.array2d(dtype=wp.mat33)):
    w, k = wp.tid()
    mv.rate[w, k] = points.point_rate(mv.slope, k, qpos[w, mv.qpos[k]], mv.site[k], mv.neighbours[k],
                                      xmat[w, mv.body[k]], site_xpos[w])


@wp.kernel
def _muscle_actuation(mu: Muscles, mv: Moving, dt: float, substeps: int, qpos: wp.array2d(dtype=float),
                      qvel: wp.array2d(dtype=float), ten_length: wp.array2d(dtype=float),
                      ten_velocity: wp.array2d(dtype=float), ctrl: wp.array2d(dtype=float),
                      biasprm: wp.array2d(dtype=wp.types.vector(length=10, dtype=float))):
    """`physics._muscle_actuation` for one world and muscle, with the moving points' share of
    its lengthening speed: each muscle pulls through the tendon its conditional point selects,
    ctrl + bias·(tendon velocity) = -(end force + stiffness·dt·(change of that velocity))."""
    w, i = wp.tid()
    row = mu.switch_row[i]
    tendon = points.selected_tendon(mu.on[i], row, mu.switch_qpos, mu.low, mu.high, mu.off_tendon, qpos[w])
    mu.tendon[w, i] = tendon
    speed = float(ten_velocity[w, tendon])
    for k in range(mv.tendon.shape[0]):
        if mv.tendon[k] == tendon:
            speed += mv.rate[w, k] * qvel[w, mv.dof[k]]
    a, lce, force, stiffness = muscles.advance_one(mu.activation[w, i], mu.fiber[w, i], mu.excitation[w, i],
                                                   ten_length[w, tendon], speed, dt, substeps, mu.params[w, i])
    mu.activation[w, i] = a
    mu.fiber[w, i] = lce
    # the idle tendon and actuator of a switching muscle carry nothing
    mu.tension[w, mu.on[i]] = 0.0
    driven = i
    if row >= 0:
        mu.tension[w, mu.off_tendon[row]] = 0.0
        idle = mu.off_actuator[row]
        if tendon == mu.off_tendon[row]:
            driven = idle
            idle = i
        ctrl[w, idle] = 0.0
        bias = biasprm[w, idle]
        bias[2] = 0.0
        biasprm[w, idle] = bias
    mu.tension[w, tendon] = force
    ctrl[w, driven] = stiffness * dt * ten_velocity[w, tendon] - force
    bias = biasprm[w, driven]
    bias[2] = -stiffness * dt
    biasprm[w, driven] = bias


@wp.kernel
def _point_torques(mv: Moving, tension: wp.array2d(dtype=float), ctrl: wp.array2d(dtype=float)):
    w, j = wp.tid()
    a = mv.torque_actuators[j]
    ctrl[w, a] = points.point_torque(a, mv.actuator, mv.tendon, mv.rate[w], tension[w])


@wp.kernel
def _contact_actuation(ft: Feet, course: wp.array2d(dtype=wp.vec3), geom_xpos: wp.array2d(dtype=wp.vec3),
                       xpos: wp.array2d(dtype=wp.vec3), xipos: wp.array2d(dtype=wp.vec3),
                       xmat: wp.array2d(dtype=wp.mat33), cvel: wp.array2d(dtype=wp.spatial_vector),
                       subtree_com: wp.array2d(dtype=wp.vec3), site_pos: wp.array2d(dtype=wp.vec3),
                       site_xpos: wp.array2d(dtype=wp.vec3), actuator_velocity: wp.array2d(dtype=float),
                       ctrl: wp.array2d(dtype=float), biasprm: wp.array2d(dtype=wp.types.vector(length=10, dtype=float)),
                       xfrc_applied: wp.array2d(dtype=wp.spatial_vector)):
    """`physics._contact_actuation` with the ground forces, for one world and sphere: the contact
    site moves to the contact point, ctrl cancels the actuator speed MuJoCo took at its old place;
    and the obstacles' force on the sphere as its body's applied force (each sphere alone on its
    body)."""
    w, i = wp.tid()
    b = ft.body[i]
    push, moment = feet.obstacle_push(course[w], ft.radius[i], geom_xpos[w, ft.sphere[i]], xipos[w, b], cvel[w, b],
                                      subtree_com[w, ft.root[i]])
    ft.obstacle_force[w, i] = push
    xfrc_applied[w, b] = wp.spatial_vector(push, moment)
    point, local, force, damping = feet.foot_force(ft.law[w], ft.radius, ft.sphere, ft.body, ft.root, ft.element, w, i,
                                                   geom_xpos, xpos, xmat, cvel, subtree_com)
    ft.force[w, i] = force
    site_pos[w, ft.site[i]] = local
    site_xpos[w, ft.site[i]] = point
    for axis in range(2):
        a = ft.x_actuator[i]
        if axis == 1:
            a = ft.y_actuator[i]
        ctrl[w, a] = force[axis] - damping[axis] * actuator_velocity[w, a]
        bias = biasprm[w, a]
        bias[2] = damping[axis]
        biasprm[w, a] = bias


@wp.kernel
def _ligaments(lg: Ligaments, qpos: wp.array2d(dtype=float), qfrc_applied: wp.array2d(dtype=float),
               dof_damping: wp.array2d(dtype=float)):
    """`physics._place`'s ligaments: springs as applied forces, damping as joint damping."""
    w, i = wp.tid()
    spring, damping = limits.engage_one(lg.table, i, qpos[w, lg.qpos[i]])
    lg.spring[w, i] = spring
    lg.damping[w, i] = damping
    qfrc_applied[w, lg.dof[i]] = spring
    dof_damping[w, lg.dof[i]] = damping


@wp.kernel
def _read_state(mu: Muscles, ft: Feet, lg: Ligaments, course: wp.array2d(dtype=wp.vec3), qpos: wp.array2d(dtype=float),
                qvel: wp.array2d(dtype=float), ten_length: wp.array2d(dtype=float), geom_xpos: wp.array2d(dtype=wp.vec3),
                xpos: wp.array2d(dtype=wp.vec3), xipos: wp.array2d(dtype=wp.vec3), xmat: wp.array2d(dtype=wp.mat33),
                cvel: wp.array2d(dtype=wp.spatial_vector), subtree_com: wp.array2d(dtype=wp.vec3)):
    """What the env reports of each world's current state: muscle lengths and tendon forces,
    ground and obstacle forces, whole ligament forces."""
    w = wp.tid()
    for i in range(mu.on.shape[0]):
        tendon = points.selected_tendon(mu.on[i], mu.switch_row[i], mu.switch_qpos, mu.low, mu.high, mu.off_tendon, qpos[w])
        mu.tendon[w, i] = tendon
        mu.length[w, i] = ten_length[w, tendon]
        mu.force[w, i] = muscles.tendon_force(mu.fiber[w, i], mu.length[w, i], mu.params[w, i])
    for i in range(ft.sphere.shape[0]):
        point, local, force, damping = feet.foot_force(ft.law[w], ft.radius, ft.sphere, ft.body, ft.root, ft.element, w,
                                                       i, geom_xpos, xpos, xmat, cvel, subtree_com)
        ft.force[w, i] = force
        b = ft.body[i]
        push, moment = feet.obstacle_push(course[w], ft.radius[i], geom_xpos[w, ft.sphere[i]], xipos[w, b], cvel[w, b],
                                          subtree_com[w, ft.root[i]])
        ft.obstacle_force[w, i] = push
    for i in range(lg.dof.shape[0]):
        lg.force[w, i] = lg.spring[w, i] - lg.damping[w, i] * qvel[w, lg.dof[i]]


@wp.kernel
def _place_obstacles(geoms: wp.array(dtype=int), course: wp.array2d(dtype=wp.vec3), reset: wp.array(dtype=int),
                     geom_pos: wp.array2d(dtype=wp.vec3), geom_size: wp.array2d(dtype=wp.vec3),
                     geom_xpos: wp.array2d(dtype=wp.vec3)):
    """The obstacle spheres of the worlds being reset at their course's (x, y, radius)."""
    w, i = wp.tid()
    if reset[w] >= 0:
        g = geoms[i]
        x, y, r = course[w, i][0], course[w, i][1], course[w, i][2]
        geom_pos[w, g] = wp.vec3(x, y, 0.0)
        # MuJoCo Warp places geoms of the world body once, in put_data, not in its kinematics.
        geom_xpos[w, g] = wp.vec3(x, y, 0.0)
        size = geom_size[w, g]
        size[0] = r
        geom_size[w, g] = size


@wp.kernel
def _equilibrate(mu: Muscles, reset: wp.array(dtype=int)):
    """Muscles of the worlds being reset at their strengths, fibre and slack lengths (as
    `thelen.scale_muscles` scales them) and activation, fibres in equilibrium, still."""
    w, i = wp.tid()
    if reset[w] >= 0:
        row = mu.table[i]
        row[muscles.MAX_FORCE] *= mu.strength[w, i]
        fiber = mu.fiber_scale[w, i]
        row[muscles.OPTIMAL_LENGTH] *= fiber
        row[muscles.WIDTH] *= fiber
        row[muscles.MAX_SPEED] *= fiber
        row[muscles.MIN_FIBER_LENGTH] *= fiber
        row[muscles.SLACK_LENGTH] *= mu.slack_scale[w, i]
        mu.params[w, i] = row
        mu.excitation[w, i] = 0.0
        mu.next_excitation[w, i] = 0.0
        mu.activation[w, i] = thelen.DEFAULT_ACTIVATION
        mu.fiber[w, i] = muscles.equilibrium_fiber_length(mu.activation[w, i], mu.length[w, i], mu.params[w, i])


@wp.kernel
def _take_excitation(mu: Muscles, substep: int):
    """From its delay on, a world's physics steps hold the excitations the env asked for."""
    w, i = wp.tid()
    if substep >= mu.delay[w]:
        mu.excitation[w, i] = mu.next_excitation[w, i]


class WarpPhysics:
    """The muscles', feet's, path points' and ligaments' state of N worlds of one MjModel on a
    Warp device, and the launches that advance it with MuJoCo Warp's step.

    `model` and `data` are MuJoCo Warp's; the public arrays (world, item) are updated in place:
    `next_excitation` is written by the env before `step`, which holds the last step's
    `excitation` over each world's first `delay` physics steps (0 at first) and it over the rest;
    `strength`, `fiber_scale` and `slack_scale` (each muscle's max isometric force, optimal fibre
    length and tendon slack length as fractions of the .osim's, 1 at first), `contact_law` (the
    feet's `ContactLaw.table`) are the next episode's, which the env may write before resetting
    a world; `obstacles` is each world's course (x, y, radius per obstacle sphere, where the model
    parks them when unused), which the env writes whole with a reset; `params` is the muscles'
    table per world, the scales applied. With `per_world_bodies` each world has its own segment
    masses and inertias in `model` (`BODY_FIELDS`), which the env may write before resetting a
    world.
    """

    def __init__(self, m: mujoco.MjModel, osim: Osim, muscle_list: list[Muscle], nworld: int, keyframe: int,
                 graphs: bool = True, per_world_bodies: bool = False):
        self.nworld, self.dt, self._keyframe = nworld, float(m.opt.timestep), keyframe
        self._device, self._graphs = wp.get_device(), {} if graphs else None
        self._reset_keys = wp.zeros(nworld, dtype=int)  # per world: the keyframe to reset to, or -1
        d = mujoco.MjData(m)
        mujoco.mj_resetDataKeyframe(m, d, keyframe)
        mujoco.mj_forward(m, d)
        batched = PER_WORLD_FIELDS + (BODY_FIELDS if per_world_bodies else ())
        self.model = mjw.put_model(m, batch_sizes={f: nworld for f in batched})
        self.data = mjw.put_data(m, d, nworld=nworld)
        n = len(muscle_list)

        switches = PathSwitches(m, muscle_list)
        mu = Muscles()
        table = thelen.muscle_parameters(muscle_list)
        mu.table = wp.array(table.astype(np.float32), dtype=muscles.MuscleRow)
        for name in ("strength", "fiber_scale", "slack_scale"):
            setattr(mu, name, wp.ones((nworld, n), dtype=float))
        mu.params = wp.array(np.broadcast_to(table, (nworld, *table.shape)).astype(np.float32), dtype=muscles.MuscleRow)
        for name in ("excitation", "next_excitation", "activation", "fiber", "length", "force"):
            setattr(mu, name, wp.zeros((nworld, n), dtype=float))
        mu.delay = wp.zeros(nworld, dtype=int)
        mu.tendon = wp.array(np.broadcast_to(switches.on, (nworld, n)).astype(np.int32), dtype=int)
        mu.tension = wp.zeros((nworld, m.ntendon), dtype=float)
        mu.on, mu.switch_row, mu.switch_qpos = _ints(switches.on), _ints(points.switch_of_muscle(switches)), _ints(switches.qpos)
        mu.low, mu.high = _floats(switches.low), _floats(switches.high)
        mu.off_tendon, mu.off_actuator = _ints(switches.off_tendon), _ints(switches.off_actuator)
        self._muscles = mu

        moving = MovingPoints(m, osim, muscle_list)
        mv = Moving()
        position, slope = points.moving_tables(moving)
        mv.table, mv.slope = wp.array(position, dtype=wp.vec3), wp.array(slope, dtype=wp.vec3)
        mv.qpos, mv.site, mv.body = _ints(moving.qpos), _ints(moving.site), _ints(moving.body)
        mv.neighbours = wp.array(moving.neighbours.astype(np.int32), dtype=wp.vec2i)
        mv.tendon, mv.dof, mv.actuator = _ints(moving.tendon), _ints(moving.dof), _ints(moving.actuator)
        mv.torque_actuators = _ints(moving.torque_actuators)
        mv.rate = wp.zeros((nworld, len(moving.site)), dtype=float)
        self._moving = mv

        names = body.CONTACT_SPHERES
        spheres = np.array([m.geom(g).id for g in names])
        sphere_body = m.geom_bodyid[spheres]
        ft = Feet()
        law = contact_law(osim).table()
        ft.law, ft.radius = _floats(np.broadcast_to(law, (nworld, len(law)))), _floats(m.geom_size[spheres, 0])
        ft.sphere, ft.body, ft.root = _ints(spheres), _ints(sphere_body), _ints(m.body_rootid[sphere_body])
        ft.element = _ints(contact_elements(osim, names))
        ft.site = _ints([m.site(f"{g}_contact").id for g in names])
        ft.x_actuator = _ints([m.actuator(f"{g}_x").id for g in names])
        ft.y_actuator = _ints([m.actuator(f"{g}_y").id for g in names])
        ft.force = wp.zeros((nworld, len(names)), dtype=wp.vec2)
        ft.obstacle_force = wp.zeros((nworld, len(names)), dtype=wp.vec3)
        self._feet = ft

        lim = default_limits()
        joints = [m.joint(c).id for c in lim.coordinates]
        lg = Ligaments()
        lg.table = _floats(ligament_table(lim))
        lg.qpos, lg.dof = _ints(m.jnt_qposadr[joints]), _ints(m.jnt_dofadr[joints])
        for name in ("spring", "damping", "force"):
            setattr(lg, name, wp.zeros((nworld, len(joints)), dtype=float))
        self._ligaments = lg

        coupling = KneeCoupling(m, osim, body.KNEE_SLIDES)
        self._equality, self._knee = _ints(coupling.equality), _ints(coupling.knee)
        self._projection = knees.Projection(coupling, nworld, m.nv)

        obstacles = [m.geom(g).id for g in body.OBSTACLES]
        self._obstacle_geoms = _ints(obstacles)
        course = np.column_stack([m.geom_pos[obstacles, :2], m.geom_size[obstacles, 0]])
        self.obstacles = wp.array(np.broadcast_to(course, (nworld, *course.shape)).astype(np.float32), dtype=wp.vec3)

    # The state the env reads, (world, item) arrays on the device.
    @property
    def params(self) -> wp.array:
        return self._muscles.params

    @property
    def strength(self) -> wp.array:
        return self._muscles.strength

    @property
    def fiber_scale(self) -> wp.array:
        return self._muscles.fiber_scale

    @property
    def slack_scale(self) -> wp.array:
        return self._muscles.slack_scale

    @property
    def contact_law(self) -> wp.array:
        return self._feet.law

    @property
    def delay(self) -> wp.array:
        return self._muscles.delay

    @property
    def excitation(self) -> wp.array:
        return self._muscles.excitation

    @property
    def next_excitation(self) -> wp.array:
        return self._muscles.next_excitation

    @property
    def activation(self) -> wp.array:
        return self._muscles.activation

    @property
    def fiber(self) -> wp.array:
        return self._muscles.fiber

    @property
    def muscle_length(self) -> wp.array:
        return self._muscles.length

    @property
    def muscle_force(self) -> wp.array:
        return self._muscles.force

    @property
    def ground_force(self) -> wp.array:
        return self._feet.force

    @property
    def obstacle_force(self) -> wp.array:
        return self._feet.obstacle_force

    @property
    def ligament_force(self) -> wp.array:
        return self._ligaments.force

    def reset(self, worlds: np.ndarray | None = None) -> None:
        """Put the worlds named (all by default) in the keyframe's pose at rest, muscles as
        OpenSim starts them. The other worlds keep their state (MuJoCo Warp's forward pass runs
        on every world, recomputing what their state already gives)."""
        keys = np.full(self.nworld, -1 if worlds is not None else self._keyframe, np.int32)
        if worlds is not None:
            keys[np.asarray(worlds)] = self._keyframe
        self._reset_keys.assign(keys)
        self._launch("reset", self._reset)

    def step(self, substeps: int) -> None:
        """Hold `excitation` over `substeps` physics steps in every world."""
        self._launch("step", lambda: self._advance(substeps), substeps)

    def _launch(self, name: str, work, *choices) -> None:
        """Run `work`'s launches, from the second time on as one Warp graph (a CUDA graph, or
        Warp's recorded replay on the CPU): a physics step is some 300 launches, each costing the
        host more than the GPU. The first run loads every kernel the graph will hold. A graph
        keeps the host's choices made when it was captured, so those (`choices`) are part of its
        key; every array it reads or writes keeps its place in memory."""
        if self._graphs is None:
            return work()
        key = (name, *choices)
        if key not in self._graphs:
            self._graphs[key] = None
            return work()
        if self._graphs[key] is None:
            try:
                with wp.ScopedCapture(self._device, force_module_load=False) as capture:
                    work()  # recorded, not run
            except Exception as e:  # noqa: BLE001  (a device or driver that cannot capture: slower, not wrong)
                log.warning("Warp could not capture the %s launches on %s (%s); launching them one by one",
                            name, self._device, e)
                self._graphs = None
                return work()
            self._graphs[key] = capture.graph
        wp.capture_launch(self._graphs[key])

    def _reset(self) -> None:
        m, d, reset = self.model, self.data, self._reset_keys
        mjw.reset_data_keyframe(m, d, reset)
        obstacles = self._obstacle_geoms
        wp.launch(_place_obstacles, self.obstacles.shape, [obstacles, self.obstacles, reset, m.geom_pos, m.geom_size,
                                                           d.geom_xpos])
        self._place()
        mjw.forward(m, d)
        self._read_state()  # the muscle lengths of the new pose
        wp.launch(_equilibrate, self._muscles.excitation.shape, [self._muscles, reset])
        self._read_state()

    def _advance(self, substeps: int) -> None:
        m, d = self.model, self.data
        for substep in range(substeps):
            wp.launch(_take_excitation, self._muscles.excitation.shape, [self._muscles, substep])
            self._drive()
            mjw.transmission(m, d)  # the contact sites moved: their actuators' moment arms
            mjw.step2(m, d)
            self._projection(m, d)
            self._place()
            mjw.step1(m, d)
        self._read_state()

    def _drive(self) -> None:
        m, d, mu, mv = self.model, self.data, self._muscles, self._moving
        wp.launch(_rates, mv.rate.shape, [mv, d.qpos, d.site_xpos, d.xmat])
        wp.launch(_muscle_actuation, mu.activation.shape,
                  [mu, mv, self.dt, FIBER_SUBSTEPS, d.qpos, d.qvel, d.ten_length, d.ten_velocity, d.ctrl, m.actuator_biasprm])
        wp.launch(_point_torques, (self.nworld, mv.torque_actuators.shape[0]), [mv, mu.tension, d.ctrl])
        wp.launch(_contact_actuation, self._feet.force.shape,
                  [self._feet, self.obstacles, d.geom_xpos, d.xpos, d.xipos, d.xmat, d.cvel, d.subtree_com, m.site_pos,
                   d.site_xpos, d.actuator_velocity, d.ctrl, m.actuator_biasprm, d.xfrc_applied])

    def _place(self) -> None:
        m, d, mv, lg = self.model, self.data, self._moving, self._ligaments
        wp.launch(_ligaments, lg.spring.shape, [lg, d.qpos, d.qfrc_applied, m.dof_damping])
        wp.launch(points.place_points, mv.rate.shape, [mv.table, mv.qpos, mv.site, d.qpos, m.site_pos])
        projection = self._projection
        wp.launch(knees.follow_splines, (self.nworld, self._equality.shape[0]),
                  [self._equality, self._knee, projection.breaks, projection.cubics, d.qpos, m.eq_data])

    def _read_state(self) -> None:
        d = self.data
        wp.launch(_read_state, self.nworld, [self._muscles, self._feet, self._ligaments, self.obstacles, d.qpos, d.qvel,
                                             d.ten_length, d.geom_xpos, d.xpos, d.xipos, d.xmat, d.cvel, d.subtree_com])
