"""Wire codec: a message model ⇄ msgpack bytes of its `model_dump()` (DESIGN.md, "Messages").

The kind travels in the Zenoh encoding, `application/msgpack;<Model>`, so a receiver knows
what it got before decoding. Every failure — bad bytes, a truncated payload, an unknown or
unexpected kind, a field that does not validate — raises `CodecError` and nothing else.
"""

from __future__ import annotations

import msgpack
from pydantic import ValidationError

from schemas import MESSAGES
from schemas.base import Message
from services.common.errors import GridslamError

ENCODING_PREFIX = "application/msgpack;"
MODELS: dict[str, type[Message]] = {model.KIND: model for model in MESSAGES}


class CodecError(GridslamError):
    """A payload could not be decoded into the expected message."""


def encoding_of(model: type[Message] | Message) -> str:
    """The Zenoh encoding string for a message model (or instance)."""
    return ENCODING_PREFIX + model.KIND


def kind_of(encoding: str) -> str:
    """The message kind named by a Zenoh encoding string; CodecError when it names none."""
    if not encoding.startswith(ENCODING_PREFIX):
        raise CodecError(f"encoding {encoding!r} is not {ENCODING_PREFIX}<Model>")
    kind = encoding[len(ENCODING_PREFIX):]
    if kind not in MODELS:
        raise CodecError(f"unknown message kind {kind!r}")
    return kind


def encode(message: Message) -> bytes:
    return msgpack.packb(message.model_dump(), use_bin_type=True)


def decode(payload: bytes, expected: type[Message] | None = None, encoding: str | None = None) -> Message:
    """Decode `payload` into `expected`, or into the model named by `encoding` when `expected` is None.

    When both are given they must agree (a wrong kind on a topic is an error, not a guess)."""
    if encoding is not None:
        kind = kind_of(encoding)
        if expected is not None and kind != expected.KIND:
            raise CodecError(f"wrong message kind {kind!r}, expected {expected.KIND!r}")
        expected = expected or MODELS[kind]
    if expected is None:
        raise CodecError("no message kind given: pass the expected model or the encoding")
    try:
        fields = msgpack.unpackb(payload, raw=False, strict_map_key=True)
    except (ValueError, msgpack.ExtraData, msgpack.FormatError, msgpack.StackError, TypeError) as error:
        raise CodecError(f"{expected.KIND}: payload of {len(payload)} bytes is not valid msgpack ({error})") from None
    if not isinstance(fields, dict):
        raise CodecError(f"{expected.KIND}: payload is a msgpack {type(fields).__name__}, expected a map")
    try:
        return expected.model_validate(fields)
    except ValidationError as error:
        first = error.errors()[0]
        where = ".".join(str(part) for part in first["loc"]) or "(message)"
        raise CodecError(f"{expected.KIND}: field {where}: {first['msg']} ({error.error_count()} error(s))") from None
