"""The MuJoCo body of the runner: where it lives, how to load it, and the names the env uses.

Frames are OpenSim's: the body moves in the x-y plane, y up, gravity along -y. Joints carry the
.osim coordinate names and units (rad, m); the knee's coupled tibia translation uses the extra
slide joints `knee_tx_*`/`knee_ty_*`. Keyframe "default" is the .osim default pose.
"""

from __future__ import annotations

import functools
from pathlib import Path

import mujoco
import numpy as np

from l2r.sim.knee import KneeCoupling
from l2r.sim.opensim import read_osim

MODEL_PATH = Path(__file__).parent / "assets" / "runner.xml"
OSIM_PATH = Path(__file__).parent / "assets" / "gait9dof18musc.osim"  # the OpenSim model it ports

# Action order: the .osim muscle order (right leg, then left).
MUSCLES = (
    "hamstrings_r", "bifemsh_r", "glut_max_r", "iliopsoas_r", "rect_fem_r",
    "vasti_r", "gastroc_r", "soleus_r", "tib_ant_r",
    "hamstrings_l", "bifemsh_l", "glut_max_l", "iliopsoas_l", "rect_fem_l",
    "vasti_l", "gastroc_l", "soleus_l", "tib_ant_l",
)  # fmt: skip
# The .osim coordinates (joint names in the MJCF), in the .osim order.
COORDINATES = (
    "pelvis_tilt", "pelvis_tx", "pelvis_ty",
    "hip_flexion_r", "knee_angle_r", "ankle_angle_r",
    "hip_flexion_l", "knee_angle_l", "ankle_angle_l",
)  # fmt: skip
LEG_COORDINATES = COORDINATES[3:]
BODIES = (
    "pelvis", "femur_r", "tibia_r", "talus_r", "calcn_r", "toes_r",
    "femur_l", "tibia_l", "talus_l", "calcn_l", "toes_l", "torso", "head",
)  # fmt: skip
CONTACT_SPHERES = ("r_heel", "r_toe", "l_heel", "l_toe")
GROUND = "ground"
OBSTACLES = ("obstacle_0", "obstacle_1", "obstacle_2")
KNEE_SLIDES = {"knee_angle_r": ("knee_tx_r", "knee_ty_r"), "knee_angle_l": ("knee_tx_l", "knee_ty_l")}
DEFAULT_KEYFRAME = "default"


def load_model(path: Path | str = MODEL_PATH) -> mujoco.MjModel:
    """Compile the runner MJCF (the packaged one by default)."""
    return mujoco.MjModel.from_xml_path(str(path))


def set_pose(model: mujoco.MjModel, data: mujoco.MjData, pose: dict[str, float]) -> None:
    """Set coordinates by name and move the knee slides to where OpenSim's splines put them.

    Coordinates not named keep their current values; call `mujoco.mj_forward` afterwards.
    """
    for name, value in pose.items():
        data.qpos[model.joint(name).qposadr[0]] = value
    coupling = _knee_coupling()
    for k, (knee, slide) in enumerate(zip(coupling.knee_names, coupling.slide_names)):
        address = model.joint(slide).qposadr[0]
        data.qpos[address] = model.qpos0[address] + coupling.slide_position(k, data.qpos[model.joint(knee).qposadr[0]])


@functools.cache
def _knee_coupling() -> KneeCoupling:
    return KneeCoupling(load_model(), read_osim(OSIM_PATH), KNEE_SLIDES)


def reset_to_default(model: mujoco.MjModel, data: mujoco.MjData) -> None:
    """Put the body in the .osim default pose, at rest, with all activations zero."""
    mujoco.mj_resetDataKeyframe(model, data, model.keyframe(DEFAULT_KEYFRAME).id)
    mujoco.mj_forward(model, data)

