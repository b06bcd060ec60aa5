"""Acquired views on the wire: posed frames (images, depth) sent as observations, commits, and
the views read back."""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, model_validator

from agilegs.config.types import integral

from .arrays import B64Bytes, NDArray
from .fields import MAX_OBSERVATIONS_WIRE, STRICT, Id, narrowed
from .forms import Form, one_of
from .geometry import Intrinsics, Pose

__all__ = [
    "CommitRequest",
    "Frame",
    "FramesOut",
    "FramesRequest",
    "ImageData",
    "InitialFrame",
    "ObservationIn",
    "ObservationsIn",
    "View",
    "ViewsOut",
    "frames_in",
]


class ImageData(BaseModel):
    """An RGB image: ``png`` or ``jpeg`` file bytes, or ``raw`` pixels with ``dtype``
    (uint8 0-255, or float32 0-1) and ``shape`` [H, W, 3], C order, little-endian; its
    size must match the observation's intrinsics."""

    model_config = ConfigDict(extra="forbid", strict=True, json_schema_extra=one_of([
        Form("ImageFile", ("encoding", "data"), ("dtype", "shape"),
             {"encoding": {"type": "string", "enum": ["png", "jpeg"]}}),
        Form("ImageRaw", ("encoding", "data", "dtype", "shape"), (), {
            "encoding": {"type": "string", "const": "raw"},
            "shape": {"type": "array", "minItems": 3, "maxItems": 3, "prefixItems": [
                {"type": "integer", "minimum": 1, "maximum": 16384},
                {"type": "integer", "minimum": 1, "maximum": 16384},
                {"type": "integer", "const": 3}], "description": "[H, W, 3]"}}),
    ], rules=("array-size", "image-size")))

    encoding: Literal["png", "jpeg", "raw"]
    data: B64Bytes
    dtype: Literal["uint8", "float32"] | None = Field(default=None, description="raw only")
    shape: list[Annotated[int, Field(ge=1, le=16384), BeforeValidator(integral)]] | None = Field(
        default=None, description="raw only: [H, W, 3]"
    )

    @model_validator(mode="after")
    def _consistent(self) -> ImageData:
        if self.encoding == "raw":
            if self.dtype is None or self.shape is None:
                raise ValueError("raw images need dtype and shape")
            if len(self.shape) != 3 or self.shape[2] != 3:
                raise ValueError(f"raw image shape must be [H, W, 3], got {self.shape}")
            need = math.prod(self.shape) * np.dtype(self.dtype).itemsize
            if len(self.data) != need:
                raise ValueError(f"raw image data has {len(self.data)} bytes, needs {need}")
        elif self.dtype is not None or self.shape is not None:
            raise ValueError(f"{self.encoding} images carry no dtype or shape")
        return self

    @classmethod
    def from_numpy(cls, image: Any, encoding: Literal["raw", "png", "jpeg"] = "raw") -> ImageData:
        """Wrap an RGB image [H, W, 3] (uint8, or float in 0-1); png/jpeg need Pillow."""
        a = np.asarray(image)
        if a.ndim != 3 or a.shape[2] != 3:
            raise ValueError(f"image must have shape [H, W, 3], got {list(a.shape)}")
        if encoding == "raw":
            if a.dtype != np.uint8:
                a = a.astype("<f4")
            a = np.ascontiguousarray(a)
            dtype: Literal["uint8", "float32"] = "uint8" if a.dtype == np.uint8 else "float32"
            return cls(encoding="raw", data=a.tobytes(), dtype=dtype, shape=list(a.shape))
        import io

        from PIL import Image

        if a.dtype != np.uint8:
            a = (np.clip(a, 0, 1) * 255 + 0.5).astype(np.uint8)
        buf = io.BytesIO()
        Image.fromarray(a).save(buf, format="PNG" if encoding == "png" else "JPEG")
        return cls(encoding=encoding, data=buf.getvalue())

    def to_numpy(self) -> np.ndarray:
        """The pixels [H, W, 3] (raw: as sent; png/jpeg: uint8, decoded with Pillow)."""
        if self.encoding == "raw":
            assert self.dtype is not None and self.shape is not None
            return np.frombuffer(self.data, dtype=np.dtype(self.dtype).newbyteorder("<")).reshape(
                self.shape
            )
        import io

        from PIL import Image

        with Image.open(io.BytesIO(self.data)) as img:
            return np.asarray(img.convert("RGB"))

class ObservationIn(BaseModel):
    """A posed frame. Where it was taken, one of:

    * ``pose`` alone: a new acquired view at that pose;
    * ``candidate_id`` (with ``pose`` if the reached pose differs from the candidate's):
      acquires that candidate (as a commit does) and attaches the frame;
    * ``view_id``: attaches the frame to a view already committed (no pose: it is fixed).

    A new view updates Ĥ. ``intrinsics`` are the image's (default: the session's); the image
    and depth must be ``height`` x ``width``. Depth is [H, W] float32 in scene units, or
    uint16 multiplied by ``depth_scale``; 0 marks a missing value.
    """

    model_config = ConfigDict(extra="forbid", strict=True, json_schema_extra=one_of([
        Form("ObservationAtPose", ("pose",), ("candidate_id", "view_id"),
             description="a new acquired view at pose"),
        Form("ObservationOfCandidate", ("candidate_id",), ("view_id",),
             description="acquires the candidate (at pose, if given)"),
        Form("ObservationOfView", ("view_id",), ("pose", "candidate_id"),
             description="the frame of a view already committed"),
    ], rules=("image-size",)))

    pose: Pose | None = None
    candidate_id: Id | None = None
    view_id: Id | None = None
    intrinsics: Intrinsics | None = None
    image: ImageData | None = None
    depth: NDArray | None = Field(default=None, json_schema_extra=narrowed({
        "properties": {"dtype": {"enum": ["float32", "uint16"]},
                       "shape": {"minItems": 2, "maxItems": 2}},
        "description": "[H, W] float32 (scene units) or uint16 (times depth_scale)"}))
    depth_scale: float = Field(default=1.0, ge=1e-6, le=1e6, allow_inf_nan=False,
                               description="scene units per uint16 depth step (1e-6 to 1e6)")

    @classmethod
    def from_numpy(
        cls,
        pose: Any = None,
        *,
        image: Any = None,
        depth: Any = None,
        intrinsics: Intrinsics | dict[str, Any] | None = None,
        candidate_id: int | None = None,
        view_id: int | None = None,
        image_encoding: Literal["raw", "png", "jpeg"] = "raw",
        depth_scale: float = 1.0,
    ) -> ObservationIn:
        """An observation from numpy: ``pose`` [4, 4] (or a Pose), ``image`` [H, W, 3]
        (uint8, or float in 0-1), ``depth`` [H, W] (float32, or uint16 x ``depth_scale``)."""
        p = None
        if pose is not None:
            p = pose if isinstance(pose, Pose) else Pose.from_matrix(pose)
        img = None
        if image is not None:
            img = image if isinstance(image, ImageData) else ImageData.from_numpy(image,
                                                                                 image_encoding)
        dep = None
        if depth is not None:
            d = np.asarray(depth)
            dep = NDArray.from_numpy(d if d.dtype == np.uint16 else d.astype(np.float32))
        k = Intrinsics.model_validate(intrinsics) if intrinsics is not None else None
        return cls(pose=p, candidate_id=candidate_id, view_id=view_id, intrinsics=k, image=img,
                   depth=dep, depth_scale=depth_scale)

    @model_validator(mode="after")
    def _where(self) -> ObservationIn:
        if self.view_id is not None:
            if self.pose is not None or self.candidate_id is not None:
                raise ValueError("view_id takes no pose and no candidate_id")
        elif self.pose is None and self.candidate_id is None:
            raise ValueError("give pose, candidate_id, or view_id")
        if self.depth is not None:
            if self.depth.dtype not in ("float32", "uint16") or len(self.depth.shape) != 2:
                raise ValueError("depth must be a [H, W] float32 or uint16 array")
        return self

class InitialFrame(ObservationIn):
    """A frame a session starts with: an :class:`ObservationIn` at a ``pose`` (no
    ``candidate_id`` or ``view_id``: there are no candidates or views yet)."""

    model_config = ConfigDict(extra="forbid", strict=True, json_schema_extra=one_of([
        Form("InitialFrame", ("pose",), ("candidate_id", "view_id"))], rules=("image-size",)))

    @model_validator(mode="after")
    def _at_pose(self) -> InitialFrame:
        if self.candidate_id is not None or self.view_id is not None:
            raise ValueError("initial frames take a pose, not candidate_id or view_id")
        return self

def frames_in(value: Any) -> Any:
    """Initial frames given as :class:`ObservationIn` objects, as the fields they set."""
    if isinstance(value, list | tuple):
        return [{k: getattr(o, k) for k in o.model_fields_set}
                if isinstance(o, ObservationIn) and not isinstance(o, InitialFrame) else o
                for o in value]
    return value

class ObservationsIn(BaseModel):
    model_config = STRICT

    observations: list[ObservationIn] = Field(min_length=1, max_length=MAX_OBSERVATIONS_WIRE)

class CommitRequest(BaseModel):
    """Acquire a view: a candidate of the pool (removed from the pool unless
    ``keep_in_pool``), or any ``pose``. Updates Ĥ."""

    model_config = ConfigDict(extra="forbid", strict=True, json_schema_extra=one_of([
        Form("CommitCandidate", ("candidate_id",), ("pose",)),
        Form("CommitPose", ("pose",), ("candidate_id",)),
    ]))

    candidate_id: Id | None = None
    pose: Pose | None = None
    keep_in_pool: bool = False

    @model_validator(mode="after")
    def _one(self) -> CommitRequest:
        if (self.candidate_id is None) == (self.pose is None):
            raise ValueError("give exactly one of candidate_id and pose")
        return self

class View(BaseModel):
    """An acquired view."""

    id: int
    pose: Pose
    candidate_id: int | None = Field(description="the candidate it was acquired from, if any")
    intrinsics: Intrinsics | None = Field(description="the image's intrinsics, if an image came")
    has_image: bool
    has_depth: bool
    created_at: float

class ViewsOut(BaseModel):
    views: list[View]
    version: int


class FramesRequest(BaseModel):
    """Which acquired views to read with their frames: the view ``view_id``, or every view
    (none given); ``depth`` false leaves the depth maps out. Over HTTP the fields are query
    parameters."""

    model_config = ConfigDict(extra="forbid")

    view_id: Id | None = Field(default=None, description="one view (default: every view)")
    depth: bool = Field(default=True, description="include the depth maps")


class Frame(BaseModel):
    """An acquired view and its frame as the server keeps it: ``image`` the file as it came
    (png / jpeg bytes unchanged, raw pixels as sent), ``depth`` [H, W] float32 in scene
    units (0: missing); None where the view has none (or the request left depth out)."""

    view: View
    image: ImageData | None = None
    depth: NDArray | None = None


class FramesOut(BaseModel):
    frames: list[Frame]
    version: int
