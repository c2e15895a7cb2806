"""The port's generalised force of a muscle about the right knee, for the moving-point tests."""

import mujoco
import numpy as np

from l2r.sim import model as body
from l2r.sim.paths import MovingPoints, PathSwitches

STEP = 1e-6  # rad, the central difference of the tendon length


def knee_torque(m: mujoco.MjModel, moving: MovingPoints, switches: PathSwitches, index: int, pose: dict,
                tension: float = 1000.0) -> tuple[float, float]:
    """(whole, moving points' share) of muscle `index`'s generalised force about knee_angle_r
    (N·m) for this tension: MuJoCo's tendon moment arm with the sites held where the pose puts
    them, plus the knee's moving-point actuator. `index` is in the muscle order `moving` and
    `switches` were built with."""
    d = mujoco.MjData(m)
    knee = pose["knee_angle_r"]

    def length(tendon, q, place):
        body.reset_to_default(m, d)
        body.set_pose(m, d, {**pose, "knee_angle_r": q})
        if place:
            moving.place(m, d.qpos)
        mujoco.mj_kinematics(m, d)
        mujoco.mj_tendon(m, d)
        return d.ten_length[tendon]

    body.set_pose(m, d, pose)
    tendon = switches.tendons(d.qpos)[index]  # the path the knee selects
    length(tendon, knee, place=True)  # the sites where the knee puts them, then held
    fixed = (length(tendon, knee + STEP, False) - length(tendon, knee - STEP, False)) / (2 * STEP)
    length(tendon, knee, place=True)
    mujoco.mj_forward(m, d)
    tensions, ctrl = np.zeros(m.ntendon), np.zeros(m.nu)
    tensions[tendon] = tension
    moving.rates(d)
    moving.torques(tensions, ctrl)
    share = ctrl[m.actuator("knee_angle_r_moving_points").id]
    return -tension * fixed + share, share
