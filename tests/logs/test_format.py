"""The record format's pieces: fast encoders against the protobuf library, and the body description
against MuJoCo itself."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import mujoco
import numpy as np
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from l2r.episodes import schema
from l2r.episodes.body import BodyModel
from l2r.episodes.encode import StepLayout, TransformEncoder, cdr_string
from l2r.sim.model import BODIES, MUSCLES, load_model

doubles = st.floats(allow_nan=True, allow_infinity=True, width=64)
Step = schema.step_message_class()


def same(a, b) -> bool:
    return np.array_equal(np.asarray(a, dtype=float), np.asarray(b, dtype=float), equal_nan=True)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])  # a busy machine is not a bug
@given(st.dictionaries(st.sampled_from([n for n, _ in schema.STEP_VECTORS]), st.integers(0, 60)),
       st.integers(0, 2**32 - 200), st.data())  # fmt: skip
def test_step_messages_decode_to_the_values_written(sizes, first_step, data):
    layout = StepLayout(sizes)
    rows = data.draw(st.integers(1, 4))
    block = layout.new_block(rows)
    for name, _ in schema.STEP_SCALARS:
        block[name] = data.draw(arrays(np.float64, rows, elements=doubles))
    for name, n in layout.sizes.items():
        if n:
            block[name] = data.draw(arrays(np.float64, (rows, n), elements=doubles))
    for i, message in enumerate(layout.messages(block, first_step, rows)):
        step = Step.FromString(message)
        assert step.step == first_step + i
        for name, _ in schema.STEP_SCALARS:
            assert same(getattr(step, name), block[name][i])
        for name, n in layout.sizes.items():
            assert same(list(getattr(step, name)), block[name][i] if n else [])


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])  # a busy machine is not a bug
@given(st.integers(0, 2**62), arrays(np.float64, (len(BODIES), 7), elements=doubles))
def test_frame_transforms_decode_to_the_poses_written(time_ns, values):
    pos, quat = values[:, :3], values[:, 3:]
    message = FrameTransforms.FromString(TransformEncoder(BODIES).encode(time_ns, pos, quat))
    first, rest = message.transforms[0], message.transforms[1:]
    assert (first.parent_frame_id, first.child_frame_id) == (schema.WORLD_FRAME, schema.GROUND_FRAME)
    assert [t.child_frame_id for t in rest] == list(BODIES)
    for t, p, q in zip(rest, pos, quat):
        assert t.parent_frame_id == schema.GROUND_FRAME and t.timestamp.ToNanoseconds() == time_ns
        assert same([t.translation.x, t.translation.y, t.translation.z], p)
        assert same([t.rotation.w, t.rotation.x, t.rotation.y, t.rotation.z], q)


def test_a_block_of_frame_transforms_mixes_timestamp_lengths():
    times = [0, 1, 127, 128, 10**9 + 5, 2**40, 1795238732414350454]
    rng = np.random.default_rng(0)
    pos, quat = rng.normal(size=(len(times), len(BODIES), 3)), rng.normal(size=(len(times), len(BODIES), 4))
    for t, p, q, raw in zip(times, pos, quat, TransformEncoder(BODIES).encode_block(times, pos, quat)):
        transforms = FrameTransforms.FromString(raw).transforms[1:]
        assert all(tr.timestamp.ToNanoseconds() == t for tr in transforms)
        assert same([[tr.translation.x, tr.translation.y, tr.translation.z] for tr in transforms], p)
        assert same([[tr.rotation.w, tr.rotation.x, tr.rotation.y, tr.rotation.z] for tr in transforms], q)


def test_cdr_string_layout():
    assert cdr_string("ab") == b"\x00\x01\x00\x00\x03\x00\x00\x00ab\x00"


def test_muscle_paths_follow_the_sites_mujoco_computes():
    m = load_model()
    d = mujoco.MjData(m)
    d.qpos[:] = m.qpos0 + np.random.default_rng(0).normal(0.0, 0.2, m.nq)
    mujoco.mj_forward(m, d)
    body = BodyModel.from_model(m)
    assert set(BODIES) <= set(body.bodies) and body.muscles == MUSCLES
    points = body.muscle_points(d.xpos[1:], d.xquat[1:])
    for name, path in zip(MUSCLES, points):  # the sites; wrapping surfaces between them are not drawn
        t = m.tendon(name).id
        start, count = m.tendon_adr[t], m.tendon_num[t]
        kinds, ids = m.wrap_type[start : start + count], m.wrap_objid[start : start + count]
        sites = ids[kinds == mujoco.mjtWrap.mjWRAP_SITE]
        assert len(sites) >= 2 and np.allclose(path, d.site_xpos[sites], atol=1e-12)


def test_the_body_renders_as_urdf_scene_and_json():
    body = BodyModel.from_model(load_model())
    obstacles = [(2.0, 0.01, 0.1), (3.5, -0.02, 0.08)]
    assert BodyModel.from_json(body.to_json()) == body

    robot = ET.fromstring(body.urdf(obstacles))
    links = {link.get("name"): link for link in robot.iter("link")}
    assert set(links) == {schema.WORLD_FRAME, schema.GROUND_FRAME, *body.bodies}
    assert sum(len(links[b].findall("visual")) for b in body.bodies) == len(body.shapes)
    assert len(links[schema.GROUND_FRAME].findall("visual")) == 1 + len(obstacles)
    assert all(links[b].findall("visual") for b in body.bodies)

    scene = SceneUpdate.FromString(body.scene_update(123, obstacles).SerializeToString())
    entities = {e.frame_id: e for e in scene.entities}
    assert set(entities) == {schema.GROUND_FRAME, *body.bodies} and all(e.frame_locked for e in scene.entities)
    assert len(entities[schema.GROUND_FRAME].spheres) == len(obstacles)
    assert all(e.spheres or e.cylinders or e.cubes for e in scene.entities)
