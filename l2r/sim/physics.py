"""The body's dynamics that MuJoCo does not compute, stepped together with MuJoCo's own.

Before every physics step the kernels compute what OpenSim computes inside its integrator and
MuJoCo does not: the Thelen muscles' activation and fibre dynamics (`thelen.py`), pulling
through the tendon each conditional path point selects and with the moving path points' share
of speed and work (`paths.py`), and the feet's Hunt-Crossley contact with the ground and the
obstacles (`contact.py`; MuJoCo's own collisions are off);
after MuJoCo's integration they set the six joint-limit ligaments (`ligaments.py`) and move the
moving points for the new joint positions. Stiff parts go to MuJoCo's implicit integrator as
damping: tendon stiffness and contact friction through their actuators' velocity bias, ligament
damping as joint damping.

A whole env step is one kernel call: the kernel calls MuJoCo's step functions itself
(`mujoco_numba.py`), since at four 2.5 ms physics steps per env step the Python between
MuJoCo's calls cost more than MuJoCo. Physics steps run as mj_step2 then mj_step1, so that
after the loop the kinematics (body positions, centre of mass, tendon lengths, sensors) describe
the final state without an extra mj_forward.

The kernels compute with numpy's error model: a diverging state gives NaN forces, which MuJoCo
catches and resets (the env ends the episode), rather than an exception inside the step.
Numba's cache checks only the file a kernel is defined in: after editing a module whose kernels
these call (thelen, contact, paths, ligaments, knee), delete `__pycache__/physics.*.nb?` here, or the
cached step keeps the old code.
"""

from __future__ import annotations

import mujoco
import numba
import numpy as np

from l2r.sim import model as body
from l2r.sim import thelen
from l2r.sim.contact import contact_elements, contact_law, ground_forces, obstacle_forces
from l2r.sim.knee import KneeCoupling, follow_splines, project
from l2r.sim.ligaments import default_limits, engage, ligament_table
from l2r.sim.mujoco_numba import mj_forward, mj_step1, mj_step2, mj_transmission
from l2r.sim.opensim import Muscle, Osim
from l2r.sim.paths import MovingPoints, PathSwitches, add_point_speeds, place_points, point_rates, point_torques, select_tendons

# Backward-Euler sub-steps of the fibre lengths per physics step. One (2.5 ms) keeps held-pose
# tendon forces within 0.6-1 % of max force (RMS) of OpenSim's and every validator target as two
# did, at 12 % more env steps/s (docs/model.md, docs/performance.md).
FIBER_SUBSTEPS = 1


class Physics:
    """The muscles', feet's, path points' and ligaments' state for one MjModel and MjData, and
    the kernels that advance it with MuJoCo's.

    The kernels take the arrays in eight groups, tuples built once here: MuJoCo's arrays, the
    muscles, the conditional points, the moving points, the feet (`body.CONTACT_SPHERES`), the
    obstacles, the ligaments (`ligaments.LIGAMENTS`) and the knee couplings (`knee.KneeCoupling`).
    The public arrays are updated in place; `params` is this episode's muscle table, `contact` its
    ground contact law (`ContactLaw.table`) and `course` its obstacles (x, y, radius; radius 0 for
    none), which the env sets before `reset`.
    """

    def __init__(self, m: mujoco.MjModel, d: mujoco.MjData, osim: Osim, muscles: list[Muscle]):
        """muscles: the .osim muscles in action order; their actuators come first in the model."""
        self._m, self._d = m, d  # alive as long as the kernels may use their addresses
        self._model, self._data = m._address, d._address  # what MuJoCo's C functions take
        self.dt = m.opt.timestep

        n = len(muscles)
        paths, moving = PathSwitches(m, muscles), MovingPoints(m, osim, muscles)
        self.params = thelen.muscle_parameters(muscles)
        self.excitation = np.zeros(n)
        self.next_excitation = np.zeros(n)  # what a delayed step turns to after its first physics steps
        self.activation = np.zeros(n)
        self.fiber = np.zeros(n)
        self.muscle_length = np.zeros(n)  # of the current state, through the selected tendons
        self.muscle_force = np.zeros(n)  # tendon forces (N) of the current state

        feet = body.CONTACT_SPHERES
        spheres = np.array([m.geom(g).id for g in feet])
        sphere_body = m.geom_bodyid[spheres].copy()
        self.ground_force = np.zeros((len(feet), 2))  # N along x and y on each sphere, of the current state
        self.contact = contact_law(osim).table()
        self.course = np.zeros((len(body.OBSTACLES), 3))
        self.obstacle_force = np.zeros((len(feet), 3))  # N on each sphere, of the current state

        limits = default_limits()
        joints = np.array([m.joint(c).id for c in limits.coordinates])
        self.ligament_force = np.zeros(len(joints))  # N·m, of the current state

        self._mujoco = (
            d.qpos, d.qvel, d.ctrl, d.actuator_velocity, d.ten_length, d.ten_velocity, d.qfrc_applied,
            d.xpos, d.xmat, d.cvel, d.subtree_com, d.geom_xpos, d.site_xpos,
            m.site_pos, m.actuator_biasprm, m.dof_damping,
        )
        self._muscles = (
            self.params, self.excitation, self.activation, self.fiber, self.muscle_length, self.muscle_force,
            paths.on.copy(),  # the tendon each muscle pulls through now
            np.zeros(n), np.zeros(n),  # tendon force at the physics step's end (N) and its stiffness (N/m)
            np.zeros(m.ntendon), np.zeros(m.ntendon),  # tension and lengthening speed per tendon
        )
        self._switches = (paths.on, paths.muscle, paths.qpos, paths.low, paths.high, paths.off_tendon, paths.off_actuator)
        self._moving = (
            moving.table, moving.slope, moving.qpos, moving.site, moving.neighbours, moving.body, moving.tendon,
            moving.dof, moving.actuator, moving.torque_actuators, moving.rate,
        )
        self._feet = (
            self.contact, m.geom_size[spheres, 0].copy(), spheres, sphere_body,
            m.body_rootid[sphere_body].copy(), contact_elements(osim, feet),
            np.array([m.site(f"{g}_contact").id for g in feet]),
            np.array([m.actuator(f"{g}_x").id for g in feet]),
            np.array([m.actuator(f"{g}_y").id for g in feet]),
            np.zeros((len(feet), 3)), np.zeros((len(feet), 3)),  # contact points in the world, in their body
            self.ground_force, np.zeros((len(feet), 2)),  # and the forces' damping along x and y
        )
        self._obstacles = (self.course, self.obstacle_force, d.xfrc_applied, d.xipos)
        self._ligaments = (
            ligament_table(limits), m.jnt_qposadr[joints].copy(), m.jnt_dofadr[joints].copy(),
            np.zeros(len(joints)), np.zeros(len(joints)),  # spring forces and engaged dampings in effect
            self.ligament_force,
        )
        coupling = KneeCoupling(m, osim, body.KNEE_SLIDES)
        self._knees = (coupling.equality, coupling.knee, coupling.slide, coupling.breaks, coupling.cubics, m.eq_data)

    def reset(self) -> None:
        """From the pose MjData holds, at rest: ligaments and moving points for the pose, one
        forward pass, and muscles as OpenSim starts them, at their default activation with
        fibres in equilibrium with their tendons."""
        self.excitation[:] = 0.0
        self.activation[:] = thelen.DEFAULT_ACTIVATION
        _start(self._model, self._data, self._mujoco, self._muscles, self._switches, self._moving, self._feet,
               self._obstacles, self._ligaments, self._knees)

    def step(self, substeps: int, delay: int = 0) -> None:
        """Hold `excitation` (in [0, 1]) over `substeps` physics steps; with a `delay`, over the
        first `delay` of them, then `next_excitation`, which `excitation` becomes, over the rest."""
        _advance(self._model, self._data, substeps, delay, self.next_excitation, self.dt, self._mujoco,
                 self._muscles, self._switches, self._moving, self._feet, self._obstacles, self._ligaments, self._knees)

    def drive(self) -> None:
        """The first part of a physics step alone: the actuators for the coming one."""
        _drive(self.dt, self._mujoco, self._muscles, self._switches, self._moving, self._feet, self._obstacles)
        mujoco.mj_transmission(self._m, self._d)


@numba.njit(cache=True, error_model="numpy")
def _advance(model, data, substeps, delay, next_excitation, dt, mj, muscles, switches, moving, feet, obstacles, ligaments,
             knees):
    """`substeps` physics steps, the excitations turning to `next_excitation` after `delay` of
    them (none when 0), then the state the env reports."""
    for k in range(substeps):
        if delay > 0 and k == delay:
            muscles[1][:] = next_excitation
        _drive(dt, mj, muscles, switches, moving, feet, obstacles)
        mj_transmission(model, data)  # the contact sites moved: their actuators' moment arms
        mj_step2(model, data)
        # the knee slides back onto their splines before anything reads the new positions
        equality, knee, slide, breaks, cubics, eq_data = knees
        qpos, qvel = mj[0], mj[1]
        project(model, data, knee, slide, breaks, cubics, qpos, qvel)
        # The ligaments and knee couplings depend on positions alone: set after the integration
        # moved the joints and before step1 computes the passive forces and the constraints.
        _place(mj, moving, ligaments, knees)
        mj_step1(model, data)
    _read_state(mj, muscles, switches, feet, obstacles, ligaments)


@numba.njit(cache=True, error_model="numpy")
def _start(model, data, mj, muscles, switches, moving, feet, obstacles, ligaments, knees):
    """`Physics.reset`'s forward pass; the ligaments and knee couplings come before it, so that
    the passive forces include their damping and the constraints follow the splines."""
    _place(mj, moving, ligaments, knees)
    mj_forward(model, data)
    params, excitation, activation, fiber, length, force, tendons, end_force, stiffness, tension, speed = muscles
    _select_lengths(mj, switches, tendons, length)
    thelen.equilibrate(params, activation, length, fiber, end_force)
    _read_state(mj, muscles, switches, feet, obstacles, ligaments)


@numba.njit(cache=True, error_model="numpy")
def _drive(dt, mj, muscles, switches, moving, feet, obstacles):
    """Muscle, moving-point and ground forces for the coming physics step, into the actuators,
    and the obstacles' forces on the feet, into MuJoCo's applied body forces.

    Each actuator's force is ctrl + bias·(its speed). The muscles' forces are those at the
    step's end with the tendon lengths moving at their current speed; the bias carries the
    tendon stiffness times the step, which MuJoCo's implicit integrator applies to the speed
    change over the step. The contacts' bias is their damping along x and y; their sites move
    to the contact points, so that (after mj_transmission) MuJoCo's speeds and moment arms are
    the points'.
    """
    (qpos, qvel, ctrl, actuator_velocity, ten_length, ten_velocity, qfrc_applied, xpos, xmat, cvel,
     subtree_com, geom_xpos, site_xpos, site_pos, biasprm, dof_damping) = mj
    params, excitation, activation, fiber, length, force, tendons, end_force, stiffness, tension, speed = muscles
    table, slope, coordinate, site, neighbours, body, tendon, dof, actuator, torque_actuators, rate = moving
    (law, radius, sphere, sphere_body, sphere_root, element, contact_site, x_actuator, y_actuator, point, local, ground,
     damping) = feet

    point_rates(slope, coordinate, site, neighbours, body, qpos, site_xpos, xmat, rate)
    speed[:] = ten_velocity
    add_point_speeds(tendon, dof, rate, qvel, speed)
    _muscle_actuation(dt, params, activation, fiber, excitation, end_force, stiffness, tension, tendons,
                      qpos, ten_length, speed, ten_velocity, ctrl, biasprm, switches)
    point_torques(torque_actuators, actuator, tendon, rate, tension, ctrl)
    ground_forces(law, radius, sphere, sphere_body, sphere_root, element, geom_xpos, xpos, xmat, cvel, subtree_com,
                  point, local, ground, damping)
    _contact_actuation(ground, damping, point, local, contact_site, x_actuator, y_actuator,
                       site_pos, site_xpos, actuator_velocity, ctrl, biasprm)
    course, obstacle_force, xfrc_applied, xipos = obstacles
    obstacle_forces(course, radius, sphere, sphere_body, sphere_root, geom_xpos, xipos, cvel, subtree_com,
                    obstacle_force, xfrc_applied)


@numba.njit(cache=True, error_model="numpy")
def _place(mj, moving, ligaments, knees):
    """Ligaments, moving points and knee couplings for the joint positions: the ligaments'
    springs in qfrc_applied and their damping in dof_damping (the body has no other joint
    damping), the moving points' sites where their coordinates put them, each knee slide's
    coupling the cubic of its spline's segment."""
    (qpos, qvel, ctrl, actuator_velocity, ten_length, ten_velocity, qfrc_applied, xpos, xmat, cvel,
     subtree_com, geom_xpos, site_xpos, site_pos, biasprm, dof_damping) = mj
    table, slope, coordinate, site, neighbours, body, tendon, dof, actuator, torque_actuators, rate = moving
    limits, qpos_adr, dof_adr, springs, dampings, total = ligaments
    engage(limits, qpos, qpos_adr, springs, dampings)
    for i in range(dof_adr.shape[0]):
        qfrc_applied[dof_adr[i]] = springs[i]
        dof_damping[dof_adr[i]] = dampings[i]
    place_points(table, coordinate, site, qpos, site_pos)
    equality, knee, slide, breaks, cubics, eq_data = knees
    follow_splines(equality, knee, breaks, cubics, qpos, eq_data)


@numba.njit(cache=True, error_model="numpy")
def _read_state(mj, muscles, switches, feet, obstacles, ligaments):
    """What the env reports of the current state: muscle lengths and tendon forces, ground
    and obstacle forces, whole ligament forces."""
    (qpos, qvel, ctrl, actuator_velocity, ten_length, ten_velocity, qfrc_applied, xpos, xmat, cvel,
     subtree_com, geom_xpos, site_xpos, site_pos, biasprm, dof_damping) = mj
    params, excitation, activation, fiber, length, force, tendons, end_force, stiffness, tension, speed = muscles
    (law, radius, sphere, sphere_body, sphere_root, element, contact_site, x_actuator, y_actuator, point, local, ground,
     damping) = feet
    limits, qpos_adr, dof_adr, springs, dampings, total = ligaments
    _select_lengths(mj, switches, tendons, length)
    thelen.tendon_forces(params, fiber, length, force)
    ground_forces(law, radius, sphere, sphere_body, sphere_root, element, geom_xpos, xpos, xmat, cvel, subtree_com,
                  point, local, ground, damping)
    course, obstacle_force, xfrc_applied, xipos = obstacles
    obstacle_forces(course, radius, sphere, sphere_body, sphere_root, geom_xpos, xipos, cvel, subtree_com,
                    obstacle_force, xfrc_applied)
    for i in range(dof_adr.shape[0]):
        total[i] = springs[i] - dampings[i] * qvel[dof_adr[i]]


@numba.njit(cache=True, error_model="numpy")
def _select_lengths(mj, switches, tendons, length):
    """The tendon each muscle pulls through at the current positions, and its length."""
    (qpos, qvel, ctrl, actuator_velocity, ten_length, ten_velocity, qfrc_applied, xpos, xmat, cvel,
     subtree_com, geom_xpos, site_xpos, site_pos, biasprm, dof_damping) = mj
    on, muscle, coordinate, low, high, off_tendon, off_actuator = switches
    select_tendons(on, muscle, coordinate, low, high, off_tendon, qpos, tendons)
    for i in range(length.shape[0]):
        length[i] = ten_length[tendons[i]]


@numba.njit(cache=True, error_model="numpy")
def _muscle_actuation(dt, params, activation, fiber, excitation, force, stiffness, tension, tendons,
                      qpos, ten_length, ten_speed, ten_velocity, ctrl, biasprm, switches):
    """Advance the muscles over the coming physics step, their lengths moving at `ten_speed`,
    and set their actuators: each muscle pulls through the tendon its conditional point selects
    (the other actuator idles), with ctrl + bias·(MuJoCo's tendon velocity) = -(end force +
    stiffness·dt·(change of that velocity over the step))."""
    on_tendon, switch_muscle, switch_qpos, low, high, off_tendon, off_actuator = switches
    select_tendons(on_tendon, switch_muscle, switch_qpos, low, high, off_tendon, qpos, tendons)
    n = params.shape[0]
    length, speed = np.empty(n), np.empty(n)
    for i in range(n):
        length[i], speed[i] = ten_length[tendons[i]], ten_speed[tendons[i]]
    thelen.advance(params, activation, fiber, excitation, length, speed, dt, FIBER_SUBSTEPS, force, stiffness)
    tension[:] = 0.0
    for i in range(n):
        tension[tendons[i]] = force[i]
        ctrl[i] = stiffness[i] * dt * ten_velocity[tendons[i]] - force[i]
        biasprm[i, 2] = -stiffness[i] * dt
    for k in range(switch_muscle.shape[0]):
        i, a = switch_muscle[k], off_actuator[k]
        if tendons[i] == off_tendon[k]:
            ctrl[a], biasprm[a, 2] = ctrl[i], biasprm[i, 2]
            ctrl[i] = biasprm[i, 2] = 0.0
        else:
            ctrl[a] = biasprm[a, 2] = 0.0


@numba.njit(cache=True, error_model="numpy")
def _contact_actuation(force, damping, point, local, sites, x_actuators, y_actuators,
                       site_pos, site_xpos, actuator_velocity, ctrl, biasprm):
    """Move the contact sites to the contact points and set their x and y actuators. MuJoCo's
    actuator speeds were taken at the sites' old places; ctrl cancels them, so the force is the
    kernel's at the current state and only the speed change goes through the damping."""
    for k in range(sites.shape[0]):
        site_pos[sites[k]] = local[k]
        site_xpos[sites[k]] = point[k]
        for axis, a in ((0, x_actuators[k]), (1, y_actuators[k])):
            ctrl[a] = force[k, axis] - damping[k, axis] * actuator_velocity[a]
            biasprm[a, 2] = damping[k, axis]

