"""The observation spec: built from gymnasium spaces, its wire form, the check of data against
it at a daemon's edge, and how it travels in policy specs without troubling older actors."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
from gymnasium import spaces

from l2r.policy import check_spec, default_spec
from l2r.protocol import FieldSpec, ObservationSpec, ProtocolError

UINT8, FLOAT32 = np.dtype(np.uint8), np.dtype(np.float32)
CAMERA = spaces.Dict({"pixels": spaces.Box(0, 255, (3, 84, 84), np.uint8),
                      "state": spaces.Box(-np.inf, np.inf, (24,), np.float64)})


def reason_of(call, *args, **kwargs) -> str:
    with pytest.raises(ProtocolError) as error:
        call(*args, **kwargs)
    return error.value.reason


def test_a_box_is_the_vector_field_state_in_float32():
    runner = ObservationSpec.from_space(spaces.Box(-np.inf, np.inf, (41,), np.float32))
    assert runner == ObservationSpec.vector(41) and runner.vector_width == 41
    assert runner.fields == {"state": FieldSpec(FLOAT32, (41,))}
    hopper = ObservationSpec.from_space(spaces.Box(-np.inf, np.inf, (11,), np.float64))  # MuJoCo tasks say float64
    assert hopper == ObservationSpec.vector(11)


def test_a_dict_of_boxes_is_one_field_per_key_in_the_dicts_order():
    spec = ObservationSpec.from_space(CAMERA)
    assert list(spec.fields.items()) == [("pixels", FieldSpec(UINT8, (3, 84, 84))),
                                         ("state", FieldSpec(FLOAT32, (24,)))]
    assert spec.vector_width is None
    assert ObservationSpec.from_space(spaces.Dict({"state": spaces.Box(-1, 1, (3,))})) == ObservationSpec.vector(3)
    assert str(spec) == "{pixels: uint8[3, 84, 84], state: float32[24]}"


@pytest.mark.parametrize("space, match", [
    (spaces.Discrete(3), "Discrete space"),
    (spaces.Box(0, 9, (4,), np.int64), "dtype int64"),
    (spaces.Dict({"camera": spaces.Dict({"rgb": spaces.Box(0, 255, (3, 8, 8), np.uint8)})}), "'camera' is a Dict"),
    (spaces.Tuple((spaces.Box(-1, 1, (2,)),)), "Tuple space"),
    (spaces.Box(-1, 1, ()), "shape \\[\\], expected 1 to 3 dimensions"),
    (spaces.Dict({"left-eye": spaces.Box(0, 255, (3, 8, 8), np.uint8)}), "field name 'left-eye'"),
])
def test_other_spaces_are_refused_with_the_reason(space, match):
    with pytest.raises(ValueError, match=match):
        ObservationSpec.from_space(space)


def test_the_wire_form_is_a_list_of_named_fields_in_order():
    spec = ObservationSpec.from_space(CAMERA)
    wire = spec.to_wire()
    assert wire == [{"name": "pixels", "dtype": "uint8", "shape": [3, 84, 84]},
                    {"name": "state", "dtype": "float32", "shape": [24]}]
    assert ObservationSpec.from_wire(msgpack.unpackb(msgpack.packb(wire))) == spec
    assert ObservationSpec.from_wire(wire[::-1]) != spec  # the order is part of the spec


def field(name="pixels", dtype="uint8", shape=(3, 84, 84)) -> dict:
    return {"name": name, "dtype": dtype, "shape": list(shape) if isinstance(shape, tuple) else shape}


@pytest.mark.parametrize("raw, reason", [
    (field(), "bad_spec"),  # a field, not a list of them
    ([["pixels", "uint8", [3, 84, 84]]], "bad_spec"),
    ([{"name": "pixels", "dtype": "uint8"}], "bad_spec"),
    ([{**field(), "scale": 255}], "bad_spec"),
    ([], "bad_field"),
    ([field(f"camera{i}") for i in range(9)], "bad_field"),
    ([field(f"camera{i}") for i in range(8)] + ["junk"], "bad_field"),  # too long, before reading any field
    ([field(3)], "bad_field"),
    ([field(), field()], "bad_field"),
    ([field("")], "bad_field"),
    ([field("bad name")], "bad_field"),
    ([field("x" * 33)], "bad_field"),
    ([field("2d")], "bad_field"),
    ([field(dtype="float64")], "wrong_dtype"),
    ([field(dtype="|u1")], "wrong_dtype"),
    ([field(dtype=["uint8"])], "wrong_dtype"),
    ([field(dtype=None)], "wrong_dtype"),
    ([field(shape=())], "wrong_shape"),
    ([field(shape=(0,))], "wrong_shape"),
    ([field(shape=(-1, 4))], "wrong_shape"),
    ([field(shape=(1, 3, 84, 84))], "wrong_shape"),
    ([field(shape=[True])], "wrong_shape"),
    ([field(shape=[3.0])], "wrong_shape"),
    ([field(shape="3")], "wrong_shape"),
    ([field(shape=(3, 1024, 2048))], "oversized"),  # a 6 MiB frame
    ([field(dtype="float32", shape=(1, 1025, 1024))], "oversized"),
    ([field(shape=(2**62, 2**62, 2**62))], "oversized"),
])
def test_a_bad_spec_from_a_peer_is_rejected_with_its_reason(raw, reason):
    assert reason_of(ObservationSpec.from_wire, raw) == reason


def test_the_largest_field_is_accepted():
    assert ObservationSpec.from_wire([field(shape=(4, 1024, 1024))]).fields["pixels"].nbytes == 4 * 2**20


ROWS = {"pixels": np.zeros((5, 3, 84, 84), np.uint8), "state": np.zeros((5, 24), np.float32)}


@pytest.mark.parametrize("change, reason", [
    ({"depth": np.zeros((5, 1, 84, 84), np.uint8)}, "unknown_field"),
    ({"state": None}, "missing_field"),
    ({"pixels": np.zeros((5, 3, 84, 84), np.float32)}, "wrong_dtype"),
    ({"state": np.zeros((5, 24), np.float64)}, "wrong_dtype"),
    ({"pixels": np.zeros((5, 84, 84, 3), np.uint8)}, "wrong_shape"),
    ({"pixels": np.zeros((5, 1, 3, 84, 84), np.uint8)}, "wrong_shape"),
    ({"state": np.zeros(5, np.float32)}, "wrong_shape"),
])
def test_data_is_checked_against_the_spec(change, reason):
    spec = ObservationSpec.from_space(CAMERA)
    spec.check(ROWS, "experience.obs")  # rows of the spec pass
    rows = {name: array for name, array in {**ROWS, **change}.items() if array is not None}
    assert reason_of(spec.check, rows, "experience.obs") == reason


def test_one_observation_from_the_environment_becomes_the_specs_fields():
    runner = ObservationSpec.vector(3)
    fields = runner.fields_of(np.array([1.0, 2.0, 3.0]))  # float64, as gymnasium's MuJoCo tasks return it
    assert list(fields) == ["state"] and fields["state"].dtype == FLOAT32
    camera = ObservationSpec.from_space(CAMERA)
    frame = {"pixels": np.full((3, 84, 84), 7, np.uint8), "state": np.ones(24)}
    fields = camera.fields_of(frame)
    assert fields["pixels"] is frame["pixels"] and fields["state"].dtype == FLOAT32
    # never a silent cast to uint8: a float frame is an error of the environment
    assert reason_of(camera.fields_of, {**frame, "pixels": frame["pixels"] / 255.0}) == "wrong_dtype"
    assert reason_of(camera.fields_of, {**frame, "pixels": frame["pixels"][None]}) == "wrong_shape"
    assert reason_of(camera.fields_of, {"pixels": frame["pixels"]}) == "missing_field"
    assert reason_of(runner.fields_of, np.zeros(4)) == "wrong_shape"


def test_policy_specs_of_older_learners_and_checkpoints_are_the_vector():
    assert ObservationSpec.from_policy_spec(default_spec(41, 18)) == ObservationSpec.vector(41)
    assert reason_of(ObservationSpec.from_policy_spec, {"hidden": [64]}) == "bad_spec"
    assert reason_of(ObservationSpec.from_policy_spec, {"obs_dim": 41, "observation": "state"}) == "bad_spec"


def test_a_vector_policy_spec_keeps_obs_dim_so_older_actors_build_the_same_network():
    entries = ObservationSpec.vector(41).policy_entries()
    assert entries == {"observation": [{"name": "state", "dtype": "float32", "shape": [41]}], "obs_dim": 41}
    spec = {key: value for key, value in default_spec(41, 18).items() if key != "obs_dim"} | entries
    assert ObservationSpec.from_policy_spec(spec) == ObservationSpec.vector(41)
    assert check_spec(spec) == check_spec(default_spec(41, 18))  # what an actor of before compares


def test_an_image_policy_spec_is_refused_by_older_actors_for_its_missing_obs_dim():
    camera = ObservationSpec.from_space(CAMERA)
    spec = {key: value for key, value in default_spec(41, 6).items() if key != "obs_dim"} | camera.policy_entries()
    assert "obs_dim" not in spec and ObservationSpec.from_policy_spec(spec) == camera
    # An actor of before requires obs_dim (check_spec's "lacks ['obs_dim']", logged as bad_spec);
    # this one reads the observation, and its clean copy keeps obs_dim out.
    assert "obs_dim" not in check_spec(spec) and ObservationSpec.from_policy_spec(check_spec(spec)) == camera
