"""`l2r.sim.paths`' conditional and moving path points as Warp kernels over many worlds, in float32.

The tables are the numba module's (`PathSwitches`, `MovingPoints`), shared by every world; the
moving points' positions and slopes are tabulated at `paths.TABLE_STEP` over `paths.TABLE_SPAN`.
"""

from __future__ import annotations

import numpy as np
import warp as wp

# Forward only: no adjoint code to compile (half the cold compile time)
wp.set_module_options({"enable_backward": False})

from l2r.sim import paths
from l2r.sim.paths import MovingPoints, PathSwitches

TABLE_START = wp.constant(paths.TABLE_SPAN[0])
TABLE_STEP = wp.constant(paths.TABLE_STEP)


def switch_of_muscle(switches: PathSwitches) -> np.ndarray:
    """Per muscle, the row of its conditional point in the switch table, or -1."""
    row = np.full(len(switches.on), -1)
    row[switches.muscle] = np.arange(len(switches.muscle))
    return row


@wp.func
def selected_tendon(on: int, row: int, coordinate: wp.array(dtype=int), low: wp.array(dtype=float),
                    high: wp.array(dtype=float), off_tendon: wp.array(dtype=int), qpos: wp.array(dtype=float)) -> int:
    """The tendon a muscle pulls through: `on`, unless its conditional point's coordinate is
    outside the point's range (`row` is the point's row, -1 for a muscle without one)."""
    if row >= 0:
        q = qpos[coordinate[row]]
        if q < low[row] or q > high[row]:
            return off_tendon[row]
    return on


@wp.kernel
def select_tendons(on: wp.array(dtype=int), switch_row: wp.array(dtype=int), coordinate: wp.array(dtype=int),
                   low: wp.array(dtype=float), high: wp.array(dtype=float), off_tendon: wp.array(dtype=int),
                   qpos: wp.array2d(dtype=float), out: wp.array2d(dtype=int)):
    """`paths.select_tendons`, one thread per world and muscle."""
    w, i = wp.tid()
    out[w, i] = selected_tendon(on[i], switch_row[i], coordinate, low, high, off_tendon, qpos[w])


@wp.func
def _interpolate(table: wp.array2d(dtype=wp.vec3), k: int, q: float) -> wp.vec3:
    """Row k of a table at q, linearly (beyond the ends: the end segment, extrapolated)."""
    x = (q - TABLE_START) / TABLE_STEP
    i = wp.clamp(int(wp.floor(x)), 0, table.shape[1] - 2)
    t = x - float(i)
    return table[k, i] + t * (table[k, i + 1] - table[k, i])


@wp.kernel
def place_points(table: wp.array2d(dtype=wp.vec3), coord: wp.array(dtype=int), site: wp.array(dtype=int),
                 qpos: wp.array2d(dtype=float), site_pos: wp.array2d(dtype=wp.vec3)):
    """`paths.place_points`, one thread per world and moving point; `site_pos` is a per-world
    model array."""
    w, k = wp.tid()
    site_pos[w, site[k]] = _interpolate(table, k, qpos[w, coord[k]])


@wp.func
def point_rate(slope: wp.array2d(dtype=wp.vec3), k: int, q: float, site: int, neighbours: wp.vec2i,
               body_mat: wp.mat33, site_xpos: wp.array(dtype=wp.vec3)) -> float:
    """d(path length)/d(coordinate) through point k's motion: dP/dq in the world along the unit
    vectors to the point from both neighbours."""
    world = body_mat * _interpolate(slope, k, q)
    rate = float(0.0)
    for j in range(2):
        n = neighbours[j]
        if n >= 0:
            rate += wp.dot(wp.normalize(site_xpos[site] - site_xpos[n]), world)
    return rate


@wp.kernel
def point_rates(slope: wp.array2d(dtype=wp.vec3), coord: wp.array(dtype=int), site: wp.array(dtype=int),
                neighbours: wp.array(dtype=wp.vec2i), body: wp.array(dtype=int), qpos: wp.array2d(dtype=float),
                site_xpos: wp.array2d(dtype=wp.vec3), xmat: wp.array2d(dtype=wp.mat33), rate: wp.array2d(dtype=float)):
    """`paths.point_rates`, one thread per world and moving point."""
    w, k = wp.tid()
    rate[w, k] = point_rate(slope, k, qpos[w, coord[k]], site[k], neighbours[k], xmat[w, body[k]], site_xpos[w])


@wp.kernel
def add_point_speeds(tendon: wp.array(dtype=int), dof: wp.array(dtype=int), rate: wp.array2d(dtype=float),
                     qvel: wp.array2d(dtype=float), speed: wp.array2d(dtype=float)):
    """`paths.add_point_speeds`, one thread per world and moving point."""
    w, k = wp.tid()
    wp.atomic_add(speed, w, tendon[k], rate[w, k] * qvel[w, dof[k]])


@wp.func
def point_torque(actuator: int, actuators: wp.array(dtype=int), tendon: wp.array(dtype=int),
                 rate: wp.array(dtype=float), tension: wp.array(dtype=float)) -> float:
    """The generalised force of the moving points an actuator carries, for the tendons' tensions."""
    total = float(0.0)
    for k in range(actuators.shape[0]):
        if actuators[k] == actuator:
            total -= tension[tendon[k]] * rate[k]
    return total


@wp.kernel
def point_torques(torque_actuators: wp.array(dtype=int), actuator: wp.array(dtype=int), tendon: wp.array(dtype=int),
                  rate: wp.array2d(dtype=float), tension: wp.array2d(dtype=float), ctrl: wp.array2d(dtype=float)):
    """`paths.point_torques`, one thread per world and torque actuator."""
    w, j = wp.tid()
    a = torque_actuators[j]
    ctrl[w, a] = point_torque(a, actuator, tendon, rate[w], tension[w])


def moving_tables(moving: MovingPoints) -> tuple[np.ndarray, np.ndarray]:
    """The position and slope tables as (points, grid, 3) float32, for wp.vec3 arrays."""
    return moving.table.astype(np.float32), moving.slope.astype(np.float32)
