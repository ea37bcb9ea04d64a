"""The payload's schema and what a message may be, without torch or numpy: the command line checks that a
message fits the model before it loads anything (`meshseal.payload` encodes and decodes with these)."""

from __future__ import annotations

from dataclasses import dataclass

from .errors import MeshsealError

SCHEMA_VERSION = 1
KINDS = ("raw", "text", "id")  # header values 0, 1, 2; 3 is reserved
HEADER_BITS = 4


@dataclass(frozen=True)
class Schema:
    """BCH(2^m - 1, k) over GF(2^m) built on `primitive_poly`, extended by one parity bit; `d` is its
    designed distance (galois builds the code from it in one step instead of searching for k)."""

    m: int
    k: int
    d: int
    primitive_poly: str

    @property
    def payload_bits(self) -> int:
        return self.k - HEADER_BITS


SCHEMAS = {64: Schema(6, 36, 11, "x^6 + x + 1"), 32: Schema(5, 16, 7, "x^5 + x^2 + 1")}


def schema(n_bits: int) -> Schema:
    if n_bits not in SCHEMAS:
        raise MeshsealError(f"no payload schema for a model of {n_bits} bits (known: {', '.join(map(str, SCHEMAS))})")
    return SCHEMAS[n_bits]


def payload_bits(n_bits: int) -> int:
    """Message bits a model of `n_bits` raw bits carries after the header and the error correction."""
    return schema(n_bits).payload_bits


@dataclass(frozen=True)
class Message:
    """An explicit message: `Message.text("hi")`, `Message.id(123)` or `Message.raw("0101...")`."""

    kind: str
    value: str | int

    @classmethod
    def text(cls, value: str) -> "Message":
        return cls("text", value)

    @classmethod
    def id(cls, value: int) -> "Message":
        return cls("id", value)

    @classmethod
    def raw(cls, value: str) -> "Message":
        return cls("raw", value)


def payload_value(message: str | int | Message, n_bits: int) -> tuple[int, int]:
    """(kind index, payload integer) of a message; clear errors for anything that does not fit."""
    size = payload_bits(n_bits)
    if isinstance(message, Message):
        kind, value = message.kind, message.value
    elif isinstance(message, str):
        kind, value = "text", message
    elif isinstance(message, int) and not isinstance(message, bool):
        kind, value = "id", message
    else:
        raise MeshsealError(f"message must be text (str), an ID (int) or a Message, got {type(message).__name__}")
    if kind == "text":
        if not isinstance(value, str):
            raise MeshsealError("a text message must be a str")
        if "\0" in value:
            raise MeshsealError("a text message cannot contain NUL characters")
        data, limit = value.encode("utf-8"), size // 8
        if len(data) > limit:
            raise MeshsealError(f"text message is {len(data)} bytes in UTF-8; a {n_bits}-bit model carries at most "
                                f"{limit} ({size} payload bits)")
        return KINDS.index("text"), int.from_bytes(data.ljust(limit, b"\0"), "big")
    if kind == "id":
        if not isinstance(value, int) or isinstance(value, bool) or not 0 <= value < 2 ** size:
            raise MeshsealError(f"ID must be an integer from 0 to {2 ** size - 1} ({size} bits) for a {n_bits}-bit "
                                f"model, got {value!r}")
        return KINDS.index("id"), value
    if kind == "raw":
        if not isinstance(value, str) or len(value) != size or set(value) - {"0", "1"}:
            raise MeshsealError(f"a raw message must be a string of exactly {size} 0s and 1s for a {n_bits}-bit model")
        return KINDS.index("raw"), int(value, 2)
    raise MeshsealError(f"message kind must be one of {', '.join(KINDS)}, got {kind!r}")
