"""Binary payloads on the wire: bytes fields and n-dimensional arrays.

A bytes field travels as raw binary in msgpack and as a standard base64 string (RFC 4648,
with padding) in JSON; on input either form is accepted, so the same model validates a
decoded JSON body and a decoded msgpack body.

An :class:`NDArray` is ``{"dtype": "float32", "shape": [H, W], "data": <bytes>}``: the
array's elements in C (row-major) order, little-endian, ``len(data) == prod(shape) *
itemsize``.
"""

from __future__ import annotations

import base64
import binascii
import math
from typing import Annotated, Any, Literal, get_args

import numpy as np
from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    PlainSerializer,
    WithJsonSchema,
    model_validator,
)

from agilegs.config.types import integral

__all__ = ["BASE64_PATTERN", "B64Bytes", "DTYPES", "DType", "NDArray"]


BASE64_PATTERN = r"^(?:[A-Za-z0-9+/]{4})*(?:[A-Za-z0-9+/]{2}==|[A-Za-z0-9+/]{3}=)?$"
"""Standard base64 with padding (RFC 4648), as :func:`base64.b64decode` with
``validate=True`` reads it."""


def _bytes_in(value: Any) -> Any:
    if isinstance(value, str):
        try:
            return base64.b64decode(value, validate=True)
        except (binascii.Error, ValueError) as exc:
            raise ValueError("must be base64 (RFC 4648, standard alphabet)") from exc
    if isinstance(value, bytearray | memoryview):
        return bytes(value)
    return value


def _bytes_out_json(value: bytes) -> str:
    return base64.b64encode(value).decode("ascii")


B64Bytes = Annotated[
    bytes,
    BeforeValidator(_bytes_in),
    PlainSerializer(_bytes_out_json, return_type=str, when_used="json"),
    WithJsonSchema(
        {
            "type": "string",
            "contentEncoding": "base64",
            "pattern": BASE64_PATTERN,
            "description": "raw bytes in msgpack; a base64 string in JSON",
        }
    ),
]
"""Bytes: raw in msgpack, base64 text in JSON (both accepted on input)."""

DType = Literal["uint8", "uint16", "int32", "int64", "float32", "float64"]
DTYPES: tuple[str, ...] = get_args(DType)


class NDArray(BaseModel):
    """An n-dimensional array: dtype, shape, and the elements as little-endian C-order bytes
    (``data`` holds prod(shape) x itemsize bytes)."""

    model_config = ConfigDict(extra="forbid", strict=True,
                              json_schema_extra={"x-agilegs-rules": ["array-size"]})

    dtype: DType = Field(description="element type (little-endian)")
    shape: list[Annotated[int, Field(ge=0, le=2**31), BeforeValidator(integral)]] = Field(
        max_length=8, description="dimensions, outermost first"
    )
    data: B64Bytes = Field(description="prod(shape) * itemsize bytes, C order, little-endian")

    @model_validator(mode="after")
    def _check_size(self) -> NDArray:
        expected = math.prod(self.shape) * np.dtype(self.dtype).itemsize
        if len(self.data) != expected:
            raise ValueError(
                f"data has {len(self.data)} bytes but dtype {self.dtype} and shape "
                f"{self.shape} need {expected}"
            )
        return self

    def to_numpy(self) -> np.ndarray:
        """The array (a read-only view on ``data``; copy it to write)."""
        dt = np.dtype(self.dtype).newbyteorder("<")
        return np.frombuffer(self.data, dtype=dt).reshape(self.shape)

    @classmethod
    def from_numpy(cls, array: Any, dtype: str | None = None) -> NDArray:
        """Wrap ``array`` (anything ``numpy.asarray`` takes), cast to ``dtype`` if given."""
        a = np.asarray(array)
        if dtype is not None:
            a = a.astype(dtype, copy=False)
        if a.dtype.name not in DTYPES:
            raise ValueError(f"dtype {a.dtype.name} is not one of {DTYPES}")
        a = np.ascontiguousarray(a, dtype=a.dtype.newbyteorder("<"))
        return cls.model_construct(dtype=a.dtype.name, shape=list(a.shape), data=a.tobytes())
