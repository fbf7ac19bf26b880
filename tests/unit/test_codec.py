"""Codec: every message round-trips; every kind of bad payload gives CodecError."""

import math

import msgpack
import numpy as np
import pytest

from schemas import MESSAGES, GridPose
from services.common import codec
from services.common.convert import image_from_msg, image_to_msg
from tests.messages import sample_messages


def test_every_message_has_a_sample():
    assert {type(m) for m in sample_messages()} == set(MESSAGES)


@pytest.mark.parametrize("message", sample_messages(), ids=lambda m: m.KIND)
def test_round_trip(message):
    payload = codec.encode(message)
    assert isinstance(payload, bytes)
    decoded = codec.decode(payload, type(message), codec.encoding_of(message))
    assert decoded == message
    assert codec.decode(payload, encoding=codec.encoding_of(message)) == message


def test_images_travel_as_raw_bytes():
    frame = sample_messages()[0]
    unpacked = msgpack.unpackb(codec.encode(frame), raw=False)
    assert isinstance(unpacked["left"]["data"], bytes)
    assert len(unpacked["left"]["data"]) == 24 * 32


def test_image_conversion_round_trip():
    rng = np.random.default_rng(1)
    for array in (rng.integers(0, 256, (5, 7), dtype=np.uint8), rng.integers(0, 256, (5, 7, 3), dtype=np.uint8),
                  rng.random((4, 6)).astype(np.float32)):
        assert np.array_equal(image_from_msg(image_to_msg(array)), array)


def test_bad_bytes():
    with pytest.raises(codec.CodecError, match="not valid msgpack"):
        codec.decode(b"\xc1\xff\x00garbage", GridPose)


def test_truncated_payload():
    payload = codec.encode(sample_messages()[2])
    with pytest.raises(codec.CodecError):
        codec.decode(payload[: len(payload) // 2], GridPose)


def test_valid_msgpack_of_the_wrong_shape():
    with pytest.raises(codec.CodecError, match="expected a map"):
        codec.decode(msgpack.packb([1, 2, 3]), GridPose)
    with pytest.raises(codec.CodecError, match="field header"):
        codec.decode(msgpack.packb({"unexpected": 1}), GridPose)


def test_wrong_and_unknown_kind():
    payload = codec.encode(sample_messages()[2])
    with pytest.raises(codec.CodecError, match="wrong message kind 'EgoMotion'"):
        codec.decode(payload, GridPose, "application/msgpack;EgoMotion")
    with pytest.raises(codec.CodecError, match="unknown message kind 'Nope'"):
        codec.decode(payload, GridPose, "application/msgpack;Nope")
    with pytest.raises(codec.CodecError, match="is not application/msgpack"):
        codec.decode(payload, GridPose, "text/plain")


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_pose_is_rejected(bad):
    fields = sample_messages()[2].model_dump()
    fields["pose"]["position"]["x"] = bad
    with pytest.raises(codec.CodecError, match="field pose.position.x"):
        codec.decode(msgpack.packb(fields, use_bin_type=True), GridPose)


def test_image_byte_count_must_match():
    frame = sample_messages()[0]
    fields = frame.model_dump()
    fields["left"]["data"] = fields["left"]["data"][:-5]
    with pytest.raises(codec.CodecError, match="expected step × height"):
        codec.decode(msgpack.packb(fields, use_bin_type=True), type(frame))


def test_non_unit_quaternion_is_rejected():
    fields = sample_messages()[2].model_dump()
    fields["pose"]["orientation"]["w"] = 3.0
    with pytest.raises(codec.CodecError, match="not unit length"):
        codec.decode(msgpack.packb(fields, use_bin_type=True), GridPose)


def test_schema_version_from_the_future_is_rejected():
    fields = sample_messages()[2].model_dump()
    fields["schema_version"] = 99
    with pytest.raises(codec.CodecError, match="schema_version"):
        codec.decode(msgpack.packb(fields, use_bin_type=True), GridPose)


def test_every_field_is_described():
    def check(model, seen):
        if model in seen:
            return
        seen.add(model)
        for name, field in model.model_fields.items():
            assert field.description, f"{model.__name__}.{name} has no description"
            for arg in getattr(field.annotation, "__args__", ()) + (field.annotation,):
                if isinstance(arg, type) and hasattr(arg, "model_fields"):
                    check(arg, seen)
    seen = set()
    for model in MESSAGES:
        check(model, seen)
        assert model.model_config["frozen"] and model.model_config["extra"] == "forbid"
