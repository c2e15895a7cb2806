"""What OpenSim's muscle paths do that a MuJoCo tendon through fixed sites does not.

- A `ConditionalPathPoint` is part of the path only while its coordinate lies in a range: the
  knee points of the hamstrings and gastrocnemius drop out when the knee hyperextends past 10
  degrees, and the muscle-tendon length jumps. Such a muscle has two MuJoCo tendons, with and
  without the point (`<muscle>` and `<muscle>_off`), and `PathSwitches` says which one holds.
- A `MovingPathPoint` slides along its body as a function of a coordinate (the patellar
  insertion of rectus femoris and vasti on the tibia moves 6 cm with knee angle). Its site is
  moved to the spline's position before MuJoCo computes the paths (`MovingPoints.place`; OpenSim
  evaluates the splines at the coordinate clamped to its .osim range, so the point stops where
  the range ends: 2.5 mm of vasti length at 14 degrees of knee hyperextension), and
  since MuJoCo's tendon Jacobian takes every site as fixed in its body, what the point's own
  motion adds is supplied here: its share of the lengthening speed (`add_point_speeds`) and
  its work as a generalised force on the coordinate (`MovingPoints.torques`), as OpenSim's
  `GeometryPath` adds it. Both need `rates` first, at the state the points were placed in.
  OpenSim takes that share from the splines' slope at the coordinate itself, not clamped: past
  the range the point stands still, yet its speed share and generalised force go on as if it
  moved (at 10 degrees of knee hyperextension they halve the knee torque of vasti and rectus
  femoris). So do the rates here.
"""

from __future__ import annotations

import mujoco
import numba
import numpy as np

from l2r.sim.opensim import Muscle, Osim

OFF = "_off"  # suffix of a muscle's tendon, sites and actuator without its conditional point
MOVING_TORQUE = "_moving_points"  # suffix of the actuator on a coordinate that carries that work
# Moving points are tabulated over this span of their coordinate (rad) and interpolated linearly:
# at 0.5 mrad spacing the knee splines' curvature leaves errors below 0.1 µm.
TABLE_SPAN = (-3.0, 3.0)
TABLE_STEP = 5e-4
SLOPE_STEP = 1e-6  # rad, the central difference of the splines' slope


def path_points(muscle: Muscle, tendon: str) -> list:
    """The .osim points a MuJoCo tendon of this muscle runs through, in order."""
    if tendon == muscle.name:
        return list(muscle.points)
    return [p for p in muscle.points if p.kind != "conditional"]


class PathSwitches:
    """Which tendon each muscle pulls through: OpenSim drops a conditional point while its
    coordinate is outside the point's range, and so does `off`."""

    def __init__(self, model: mujoco.MjModel, muscles: list[Muscle]):
        """muscles: the .osim muscles in action order."""
        self.on = np.array([model.tendon(m.name).id for m in muscles])
        rows = []
        for i, m in enumerate(muscles):
            points = [p for p in m.points if p.kind == "conditional"]
            if points:
                rows.append((i, model.joint(points[0].coordinate).qposadr[0], *points[0].active_range,
                             model.tendon(m.name + OFF).id, model.actuator(m.name + OFF).id))
        table = np.array(rows, dtype=float).reshape(-1, 6)
        self.muscle = table[:, 0].astype(int)
        self.qpos = table[:, 1].astype(int)
        self.low, self.high = table[:, 2], table[:, 3]
        self.off_tendon = table[:, 4].astype(int)
        self.off_actuator = table[:, 5].astype(int)

    def tendons(self, qpos: np.ndarray) -> np.ndarray:
        """The tendon each muscle pulls through at these joint positions."""
        out = np.empty_like(self.on)
        select_tendons(self.on, self.muscle, self.qpos, self.low, self.high, self.off_tendon, qpos, out)
        return out


@numba.njit(cache=True, error_model="numpy")
def select_tendons(on, muscle, coordinate, low, high, off_tendon, qpos, out):
    """`PathSwitches.tendons` from its arrays, into `out`, for kernels that select in the step."""
    out[:] = on
    for k in range(muscle.shape[0]):
        q = qpos[coordinate[k]]
        if q < low[k] or q > high[k]:
            out[muscle[k]] = off_tendon[k]


class MovingPoints:
    """The moving path points of every muscle tendon: their sites, where their coordinates put
    them, and the generalised force of their motion."""

    def __init__(self, model: mujoco.MjModel, osim: Osim, muscles: list[Muscle]):
        grid = np.arange(TABLE_SPAN[0], TABLE_SPAN[1] + TABLE_STEP / 2, TABLE_STEP)
        sites, neighbours, tendons, coords, dofs, actuators, bodies, tables, slopes = [], [], [], [], [], [], [], [], []
        for m in muscles:
            for tendon in (m.name, m.name + OFF):
                if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_TENDON, tendon) < 0:
                    continue
                points = path_points(m, tendon)
                for i, p in enumerate(points):
                    if p.kind != "moving":
                        continue
                    site = model.site(f"{tendon}_{i}").id
                    sites.append(site)
                    neighbours.append((model.site(f"{tendon}_{i - 1}").id if i > 0 else -1,
                                       model.site(f"{tendon}_{i + 1}").id if i + 1 < len(points) else -1))
                    tendons.append(model.tendon(tendon).id)
                    joint = model.joint(p.coordinate)
                    coords.append(joint.qposadr[0])
                    dofs.append(joint.dofadr[0])
                    actuators.append(model.actuator(p.coordinate + MOVING_TORQUE).id)
                    bodies.append(model.site_bodyid[site])
                    q = np.clip(grid, *osim.coordinate(p.coordinate).range)
                    tables.append(np.stack([f(q) for f in p.moving], axis=1))
                    # the slope at the coordinate unclamped (a SimmSpline's end slope past its knots)
                    slopes.append(np.stack([(f(grid + SLOPE_STEP) - f(grid - SLOPE_STEP)) / (2 * SLOPE_STEP)
                                            for f in p.moving], axis=1))
        self.site = np.array(sites, dtype=int)
        self.neighbours = np.array(neighbours, dtype=int).reshape(-1, 2)
        self.tendon = np.array(tendons, dtype=int)
        self.qpos = np.array(coords, dtype=int)
        self.dof = np.array(dofs, dtype=int)
        self.actuator = np.array(actuators, dtype=int)
        self.body = np.array(bodies, dtype=int)
        self.table = np.array(tables).reshape(-1, len(grid), 3)  # positions in the body
        self.slope = np.array(slopes).reshape(-1, len(grid), 3)  # their d/dq, as OpenSim moves them
        self.torque_actuators = np.unique(self.actuator)
        self.rate = np.zeros(len(sites))  # d(path length)/d(coordinate) through each point's motion

    def place(self, model: mujoco.MjModel, qpos: np.ndarray) -> None:
        """Move the sites to where their coordinates put them (before MuJoCo's kinematics)."""
        place_points(self.table, self.qpos, self.site, qpos, model.site_pos)

    def rates(self, data: mujoco.MjData) -> None:
        """How fast each path lengthens per unit of its coordinate through the point's motion
        alone; needs the kinematics of the state the points were placed in."""
        point_rates(self.slope, self.qpos, self.site, self.neighbours, self.body, data.qpos, data.site_xpos, data.xmat, self.rate)

    def torques(self, tension: np.ndarray, ctrl: np.ndarray) -> None:
        """Set `ctrl` of the coordinates' actuators to the points' generalised force for the
        tendons' tensions (N, pulling positive, per tendon; zero for an idle tendon)."""
        point_torques(self.torque_actuators, self.actuator, self.tendon, self.rate, tension, ctrl)


@numba.njit(cache=True, error_model="numpy")
def _lookup(table: np.ndarray, q: float) -> tuple[int, float]:
    """Segment index and position within it (beyond the ends: the end segment, extrapolated)."""
    x = (q - TABLE_SPAN[0]) / TABLE_STEP
    i = min(max(int(np.floor(x)), 0), table.shape[0] - 2)
    return i, x - i


@numba.njit(cache=True, error_model="numpy")
def place_points(table, coord, site, qpos, site_pos):
    """`MovingPoints.place` from its arrays."""
    for k in range(site.shape[0]):
        i, t = _lookup(table[k], qpos[coord[k]])
        for j in range(3):
            site_pos[site[k], j] = table[k, i, j] + t * (table[k, i + 1, j] - table[k, i, j])


@numba.njit(cache=True, error_model="numpy")
def point_rates(slope, coord, site, neighbours, body, qpos, site_xpos, xmat, rate):
    """`MovingPoints.rates` from its arrays."""
    local, world, v = np.empty(3), np.empty(3), np.empty(3)
    for k in range(site.shape[0]):
        i, t = _lookup(slope[k], qpos[coord[k]])
        # dP/dq in the body, then in the world
        for c in range(3):
            local[c] = slope[k, i, c] + t * (slope[k, i + 1, c] - slope[k, i, c])
        for r in range(3):
            world[r] = 0.0
            for c in range(3):
                world[r] += xmat[body[k], 3 * r + c] * local[c]
        # d(path length)/dq through this point: the unit vectors to it from both neighbours
        rate[k] = 0.0
        for n in neighbours[k]:
            if n >= 0:
                for j in range(3):
                    v[j] = site_xpos[site[k], j] - site_xpos[n, j]
                rate[k] += np.dot(v, world) / np.sqrt(np.dot(v, v))


@numba.njit(cache=True, error_model="numpy")
def add_point_speeds(tendon, dof, rate, qvel, speed):
    """Add each point's share to its tendon's lengthening speed (`speed`, per tendon)."""
    for k in range(tendon.shape[0]):
        speed[tendon[k]] += rate[k] * qvel[dof[k]]


@numba.njit(cache=True, error_model="numpy")
def point_torques(torque_actuators, actuator, tendon, rate, tension, ctrl):
    """`MovingPoints.torques` from its arrays."""
    for a in torque_actuators:
        ctrl[a] = 0.0
    for k in range(actuator.shape[0]):
        ctrl[actuator[k]] += -tension[tendon[k]] * rate[k]
