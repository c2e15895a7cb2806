"""What each value of the Learning to Run observation and action vectors is, by name.

Both simulators build their observation in this order (docs/environment.md has the table).
The learner uses the names, without loading a simulator, to mirror a transition (right leg and
left leg swap places) and to measure x coordinates from the pelvis.
"""

from __future__ import annotations

import re

import numpy as np

PELVIS = ("pelvis_tilt", "pelvis_tx", "pelvis_ty")
JOINTS = ("hip_flexion_r", "knee_angle_r", "ankle_angle_r", "hip_flexion_l", "knee_angle_l", "ankle_angle_l")
TRACKED_BODIES = ("head", "pelvis", "torso", "toes_l", "toes_r", "talus_l", "talus_r")
LEG_MUSCLES = ("hamstrings", "bifemsh", "glut_max", "iliopsoas", "rect_fem", "vasti", "gastroc", "soleus", "tib_ant")

OBS_LABELS = (
    *PELVIS, *(f"{c}.speed" for c in PELVIS),
    *JOINTS, *(f"{c}.speed" for c in JOINTS),
    "com.x", "com.y", "com.vx", "com.vy",
    *(f"{b}.{axis}" for b in TRACKED_BODIES for axis in "xy"),
    "psoas_l", "psoas_r",
    "obstacle.dx", "obstacle.y", "obstacle.radius",
)
ACTION_LABELS = tuple(f"{m}_{side}" for side in "rl" for m in LEG_MUSCLES)
OBS_SIZE = len(OBS_LABELS)

PELVIS_X = OBS_LABELS.index("pelvis_tx")
# Absolute x coordinates in the world frame; the obstacle's dx is already measured from the pelvis.
WORLD_X = tuple(i for i, label in enumerate(OBS_LABELS) if label == "com.x" or
                (label.endswith(".x") and label.split(".")[0] in TRACKED_BODIES))


def mirror_label(label: str) -> str:
    """The name of the same quantity on the other leg: `_r` and `_l` swap, the rest stays."""
    return re.sub(r"_([rl])\b", lambda m: "_l" if m.group(1) == "r" else "_r", label)


def mirror_permutation(labels: tuple[str, ...]) -> np.ndarray:
    """Indices `p` such that `x[..., p]` is `x` with its legs swapped."""
    return np.array([labels.index(mirror_label(label)) for label in labels], dtype=np.int64)


MIRROR_OBS = mirror_permutation(OBS_LABELS)
MIRROR_ACTION = mirror_permutation(ACTION_LABELS)
