"""The episode record format: topics, schemas and metadata names shared by writer and readers.

One MCAP file holds one episode. Every channel has a registered schema, so a reader without
l2r decodes it; the encodings are the ones Rerun and Foxglove decode on their own:

    /robot_description  std_msgs/msg/String (ros2msg, CDR)   the body as URDF, once
    /scene              foxglove.SceneUpdate (protobuf)      the body, ground, obstacles, once
    /tf                 foxglove.FrameTransforms (protobuf)  every body's pose, every step
    /step               l2r.episodes.Step (protobuf)         every number of the step
    /<field>            foxglove.CompressedImage (protobuf)  every step: a camera field as PNG

The runner's episodes have the first four; a camera task's have ``/step`` (without distance and
pelvis height) and one image channel per uint8[3, H, W] field of its observation (``/pixels``);
a photo task's the same, ``/step`` with the PSNR to the goal, and its images from the observation
or, where the observation holds none (`l2r/PhotoTuneStats-v0`), from ``info["frames"]``.
Bodies are frames named as in the model; their poses are in the frame ``ground`` (the model's
frame: x forward, y up), which the frame ``world`` (z up, as the viewers expect) holds rotated.
Metadata records: ``episode`` (who, what, written first) and ``result`` (written last).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

TOPIC_ROBOT = "/robot_description"
TOPIC_SCENE = "/scene"
TOPIC_TF = "/tf"
TOPIC_STEP = "/step"
IMAGE_MESSAGE = "foxglove.CompressedImage"  # the schema of every image channel
IMAGE_FORMAT = "png"
BODY_SCALARS = ("distance", "pelvis_height")  # the runner's; a task without a body leaves them out
PHOTO_SCALARS = ("psnr_db",)  # a photo task's score after the step; other tasks leave it out


def image_topic(field: str) -> str:
    """The channel of an observation's image field: ``/pixels`` for ``pixels``."""
    return f"/{field}"


def image_fields(observation: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The camera frames of an observation's fields: its uint8[3, H, W] ones, by name (logged
    as images, and sent to live viewers)."""
    return {name: a for name, a in observation.items() if a.dtype == np.uint8 and a.ndim == 3 and a.shape[0] == 3}


WORLD_FRAME = "world"
GROUND_FRAME = "ground"

METADATA_EPISODE = "episode"  # run, actor, policy_version, seed, difficulty, env/model version, kind
METADATA_RESULT = "result"  # return, distance, length, terminated, truncated

FORMAT_VERSION = "1"
PROFILE = "l2r"

# The Step message: scalars, then one packed repeated double per vector. Field numbers are
# the wire format: never renumber, only append.
STEP_SCALARS = (("time", 2), ("reward", 3), ("distance", 4), ("pelvis_height", 5), ("psnr_db", 13))
STEP_VECTORS = (
    ("observation", 6),
    ("action", 7),
    ("muscle_activation", 8),
    ("muscle_force", 9),
    ("muscle_length", 10),
    ("ligament_force", 11),
    ("contact_force", 12),  # (foot sphere, xyz) flattened, world frame, N
)
STEP_FIELD_NUMBER = 1  # uint32, the step index from 0
STEP_MESSAGE = "l2r.episodes.Step"

# Channel metadata of /step: comma-separated names of the vector entries.
NAME_KEYS = ("muscles", "ligaments", "contacts", "bodies")


def _step_file() -> descriptor_pb2.FileDescriptorProto:
    f = descriptor_pb2.FileDescriptorProto(name="l2r/episodes/step.proto", package="l2r.episodes", syntax="proto3")
    msg = f.message_type.add(name="Step")
    Field = descriptor_pb2.FieldDescriptorProto
    msg.field.add(name="step", number=STEP_FIELD_NUMBER, type=Field.TYPE_UINT32, label=Field.LABEL_OPTIONAL)
    for name, number in STEP_SCALARS:
        msg.field.add(name=name, number=number, type=Field.TYPE_DOUBLE, label=Field.LABEL_OPTIONAL)
    for name, number in STEP_VECTORS:
        msg.field.add(name=name, number=number, type=Field.TYPE_DOUBLE, label=Field.LABEL_REPEATED)
    return f


def step_schema() -> bytes:
    """The FileDescriptorSet of ``l2r.episodes.Step``, as an MCAP protobuf schema holds it."""
    return descriptor_pb2.FileDescriptorSet(file=[_step_file()]).SerializeToString()


def step_message_class() -> type:
    """A protobuf class for ``l2r.episodes.Step`` (for readers and tests)."""
    pool = descriptor_pool.DescriptorPool()
    pool.Add(_step_file())
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(STEP_MESSAGE))


STRING_SCHEMA_NAME = "std_msgs/msg/String"
STRING_SCHEMA = b"string data"
