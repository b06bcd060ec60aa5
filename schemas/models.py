"""Request and response models of every operation (HTTP and Zenoh share them).

Poses are camera-to-world with OpenCV axes (see :mod:`agilegs.schemas.geometry`); bytes
travel raw in msgpack and base64 in JSON (see :mod:`agilegs.schemas.arrays`). Candidate and
view ids are server-assigned (or client-chosen for candidates) integers that stay stable for
the life of a session: an id is never reused for another pose.
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    StringConstraints,
    model_validator,
)
from pydantic.json_schema import JsonDict

from .arrays import B64Bytes, NDArray
from .config import (
    FIELD_NAMES,
    METHODS,
    SHORTLISTS,
    FieldName,
    MapperConfigPatch,
    Method,
    SelectConfigPatch,
    ShortlistStrategy,
)
from .forms import RULES_KEY, Form, WireInt, integral, one_of
from .geometry import Bounds, Intrinsics, Pose, PoseList, trusted_poses

__all__ = [
    "FIELD_NAMES",
    "METHODS",
    "SESSION_ID_PATTERN",
    "SHORTLISTS",
    "Candidate",
    "CommitRequest",
    "Deleted",
    "FieldName",
    "FieldSummary",
    "FileProblem",
    "GaussianArrays",
    "GaussiansIn",
    "GaussiansOut",
    "GaussiansSummary",
    "Health",
    "ImageData",
    "InformationConfig",
    "InitialFrame",
    "InformationOut",
    "InformationSummary",
    "MapperOptions",
    "MapperState",
    "MapperStatus",
    "Method",
    "ObservationIn",
    "ObservationsIn",
    "PoolIn",
    "PoolOut",
    "Repaired",
    "ScoredCandidate",
    "SelectDefaults",
    "SelectRequest",
    "SelectResponse",
    "SessionCreate",
    "SessionDamage",
    "SessionId",
    "SessionInfo",
    "SessionList",
    "SessionState",
    "SessionSummary",
    "ShortlistStrategy",
    "View",
    "ViewsOut",
]

SESSION_ID_PATTERN = r"^[A-Za-z0-9_-]{1,64}$"
SessionId = Annotated[str, StringConstraints(pattern=SESSION_ID_PATTERN)]
"""A session id: 1 to 64 characters from ``[A-Za-z0-9_-]`` (safe in URLs and Zenoh keys)."""

Id = Annotated[int, Field(ge=0, le=2**53), BeforeValidator(integral)]
MAX_POOL_WIRE = 100_000  # the schema's own cap; the server's pool_size setting is lower
MAX_OBSERVATIONS_WIRE = 256


_UNIQUE: JsonDict = {"uniqueItems": True}
_STRICT = ConfigDict(extra="forbid", strict=True)


ShortlistSize = Annotated[int, Field(ge=1, le=1024), BeforeValidator(integral)]
EmbodiedK = Annotated[int, Field(ge=1, le=100_000), BeforeValidator(integral)]
Seed = Annotated[int, Field(ge=0, le=2**63 - 1), BeforeValidator(integral)]
StepsPerView = Annotated[int, Field(ge=0, le=1_000_000), BeforeValidator(integral)]


def _unique(values: list[Any] | None, what: str) -> None:
    if values is not None and len(set(values)) != len(values):
        seen: set[Any] = set()
        for i, v in enumerate(values):
            if v in seen:
                raise ValueError(f"{what} must be unique ({what}[{i}] = {v!r} repeats)")
            seen.add(v)


def _narrowed(extra: dict[str, Any]) -> Any:
    """A field ``json_schema_extra`` that narrows the referenced model of the field (or of its
    items) with ``extra`` (``allOf`` the reference, plus ``extra``)."""

    def narrow(js: dict[str, Any]) -> None:
        for holder in ([js.get("items", {})] + list(js.get("items", {}).get("anyOf", []))
                       + list(js.get("anyOf", []))):
            if "$ref" in holder:
                ref = holder.pop("$ref")
                holder.update({"allOf": [{"$ref": ref}], **extra})

    return narrow


# ---------------------------------------------------------------------------- sessions
class SelectDefaults(BaseModel):
    """A session's selection defaults; every select request may override each of them."""

    model_config = _STRICT

    method: Method = Field(default="agile", description="selection method")
    shortlist_size: WireInt = Field(default=10, ge=1, le=1024, description="shortlist size N")
    shortlist: ShortlistStrategy = Field(
        default="leverage", description="shortlist strategy of agile / agile_plus"
    )
    embodied_k: EmbodiedK | None = Field(
        default=None,
        description="embodied mode: only the K candidates nearest the current view are eligible",
    )
    seed: WireInt = Field(default=0, ge=0, le=2**63 - 1, description="random seed")
    fields: list[FieldName] | None = Field(
        default=None, description="parameter blocks entering the information (None: all five)",
        json_schema_extra=_UNIQUE,
    )
    config: SelectConfigPatch = Field(
        default_factory=SelectConfigPatch,
        description="further SelectConfig fields, e.g. {'anchor': {'iterations': 1}}",
    )

    @model_validator(mode="after")
    def _unique_fields(self) -> SelectDefaults:
        _unique(self.fields, "fields")
        return self


class InformationConfig(BaseModel):
    """How the accumulated information Ĥ = λI + Σ_views H_v is kept.

    Ĥ is accumulated at the session's intrinsics (each acquired view's pose with the
    session camera), so it is on the scale of the H_v the selectors compute.
    """

    model_config = ConfigDict(extra="forbid", populate_by_name=True, serialize_by_alias=True,
                              strict=True)

    lambda_: float = Field(
        default=1e-3,
        alias="lambda",
        gt=0,
        le=1e12,
        allow_inf_nan=False,
        description="ridge λ added to every diagonal entry of Ĥ",
    )
    recompute_on_map_change: bool = Field(
        default=True,
        description=(
            "when the Gaussians are replaced, recompute Ĥ from every acquired view on the new "
            "map (always done when the Gaussian count changes)"
        ),
    )
    mapper_update: Literal["carry", "recompute"] = Field(
        default="carry",
        description=(
            "when the service's mapper publishes a trained map: 'carry' Ĥ over per Gaussian "
            "(kept Gaussians keep their row, clones and split children copy their source's, "
            "new Gaussians start at λ), or 'recompute' it from every acquired view on the new "
            "map (one Fisher pass per view per publication)"
        ),
    )


class MapperOptions(BaseModel):
    """How the service's mapper trains a session's Gaussians from the images sent to it.

    After each observation batch the mapper (one background worker per server) trains
    ``steps_per_view`` steps per new view with an image, on all the session's views with
    images, then idles; every burst of steps is published as the session's map (persisted,
    then visible). With ``enabled`` false (or the server's ``AGILEGS_MAPPER=0``) images are
    only stored.
    """

    model_config = _STRICT

    enabled: bool = Field(default=True, description="train this session's map from its images")
    steps_per_view: StepsPerView | None = Field(
        default=None,
        description="training steps per view with an image (None: the server's "
                    "AGILEGS_MAPPER_STEPS_PER_VIEW)",
    )
    config: MapperConfigPatch = Field(
        default_factory=MapperConfigPatch,
        description="MapperConfig fields (3DGS training settings), e.g. {'background': "
        "[1, 1, 1], 'sh_degree': 0, 'densify_from': 50}",
    )


class SessionCreate(BaseModel):
    """Create a session: empty with scene ``bounds`` (random Gaussians inside them), from
    uploaded ``gaussians``, or from initial posed ``frames`` (RGB or RGB-D).

    With RGB-D frames and no Gaussians, the map is initialised by back-projecting the depth
    (``init_gaussians`` points, coloured from the images; the depth must hold a positive
    value); with RGB frames only, from ``bounds`` when given, else the session starts without
    Gaussians (set them with ``set_gaussians``; a selection answers ``map_empty`` until then).
    Frames become acquired views (and update Ĥ). ``pool`` sets the initial candidate pool.
    """

    model_config = ConfigDict(
        extra="forbid",
        strict=True,
        # bounds, gaussians or a frame: "not none of them" (an anyOf of the three would make
        # code generators publish no model for the body)
        json_schema_extra={"not": {"properties": {
            "bounds": {"type": "null"}, "gaussians": {"type": "null"}, "frames": {"maxItems": 0}}}},
    )

    id: SessionId | None = Field(default=None, description="session id (generated if absent)")
    intrinsics: Intrinsics = Field(description="camera of the candidates and of Ĥ")
    bounds: Bounds | None = Field(default=None, description="scene bounds")
    gaussians: GaussiansIn | None = Field(default=None, description="initial Gaussians")
    frames: Annotated[list[InitialFrame], BeforeValidator(_frames_in)] = Field(
        default_factory=list, max_length=MAX_OBSERVATIONS_WIRE,
        description="initial posed frames (each with a pose; no candidate_id or view_id)",
    )
    init_gaussians: WireInt = Field(
        default=1000, ge=0, le=1_000_000, description="Gaussians created from bounds or depth"
    )
    seed: WireInt = Field(default=0, ge=0, le=2**63 - 1,
                          description="seed of the initialisation")
    pool: PoolIn | None = Field(default=None, description="initial candidate pool")
    defaults: SelectDefaults = Field(default_factory=SelectDefaults)
    information: InformationConfig = Field(default_factory=InformationConfig)
    mapper: MapperOptions = Field(default_factory=MapperOptions)

    @model_validator(mode="after")
    def _has_scene(self) -> SessionCreate:
        if self.bounds is None and self.gaussians is None and not self.frames:
            raise ValueError("give bounds, gaussians, or frames")
        return self


class GaussiansSummary(BaseModel):
    """The session's Gaussians in brief."""

    count: int
    sh_degree: int
    means_min: list[float] | None = Field(default=None, description="lower corner of the means")
    means_max: list[float] | None = Field(default=None, description="upper corner of the means")


MapperState = Literal["off", "idle", "training", "error"]


class MapperStatus(BaseModel):
    """The mapper's progress on a session.

    ``state``: ``off`` (the server's or the session's mapper is disabled), ``training``
    (steps are pending, or trained steps are not yet published), ``idle`` (every step owed
    is trained and the map holding them is published), ``error`` (training failed; see
    ``error``; new observations retry). Steps owed = ``steps_per_view`` x views with an
    image; ``pending_steps`` = owed - ``steps``.
    """

    enabled: bool
    state: MapperState
    steps: int = Field(description="training steps done (the burst in progress included)")
    published_steps: int = Field(description="training steps held by the published map")
    pending_steps: int = Field(description="steps still owed to the views sent")
    steps_per_view: int
    views: int = Field(description="acquired views with an image (what the mapper trains on)")
    num_gaussians: int = Field(description="Gaussians in the mapper's current map")
    last_loss: float | None = Field(
        default=None, description="mean training loss (L1 + D-SSIM) of the last burst"
    )
    error: str | None = None
    options: MapperOptions


class FieldSummary(BaseModel):
    """One block of Ĥ in brief (None where a value is not finite, or the block is empty)."""

    shape: list[int]
    sum: float | None
    min: float | None
    max: float | None


class InformationSummary(BaseModel):
    """Ĥ in brief: per-field shape and sums, and a digest of all its bytes."""

    fields: dict[str, FieldSummary]
    digest: str = Field(description="sha256 over every field's float32 little-endian bytes")


class FileProblem(BaseModel):
    """One state file of a session that does not check out."""

    file: str = Field(description="path under the session's folder: manifest.json, "
                                  "gaussians.<v>.pt, information.<v>.pt, pool.<v>.pt, "
                                  "views/<view>.rgb.<ext>, views/<view>.depth.npy")
    problem: str = Field(description="what is wrong: missing, truncated (n of m bytes), "
                                     "checksum mismatch, unreadable (why)")


class SessionDamage(BaseModel):
    """Why a session is damaged, and what ``repair_session`` would do about it."""

    files: list[FileProblem] = Field(description="every file that does not check out")
    version: int | None = Field(
        default=None, description="the damaged version (None: its manifest is unreadable)")
    repairable: bool = Field(
        description="whether repair_session can bring the session back; if not, delete it or "
                    "restore its folder from a backup")
    rollback_to: int | None = Field(
        default=None, description="repair_session rolls the session back to this intact "
                                  "earlier version (what later versions changed is lost)")
    drop_frames: list[int] = Field(
        default_factory=list, description="views whose damaged image / depth repair_session "
                                          "drops (the views, their poses and Ĥ stay)")
    repair: str = Field(description="what repair_session would do, in words")
    detected_at: float = Field(description="unix time (s) the damage was found")


SessionState = Literal["ok", "damaged"]


class SessionSummary(BaseModel):
    id: str
    state: SessionState = Field(
        default="ok", description="damaged: the session's files on disk do not check out "
                                  "(see damage); its operations answer 409 session_damaged, "
                                  "but for repair_session and delete_session")
    version: int | None = Field(description="incremented by every acknowledged state change "
                                            "(None: damaged and unknown)")
    num_gaussians: int | None = Field(description="None: damaged and unknown")
    pool_size: int | None = Field(description="None: damaged and unknown")
    num_views: int | None = Field(description="None: damaged and unknown")
    updated_at: float | None = Field(description="None: damaged and unknown")
    damage: SessionDamage | None = Field(default=None, description="what is damaged (state "
                                                                   "damaged only)")


class SessionInfo(BaseModel):
    """A session's state (its arrays are read through their own operations)."""

    id: str
    created_at: float = Field(description="unix time (s)")
    updated_at: float = Field(description="unix time (s) of the last state change")
    version: int = Field(description="incremented by every acknowledged state change")
    intrinsics: Intrinsics
    bounds: Bounds | None
    defaults: SelectDefaults
    information_config: InformationConfig
    gaussians: GaussiansSummary
    information: InformationSummary
    pool_size: int
    next_candidate_id: int
    num_views: int
    last_view_id: int | None
    mapper: MapperStatus | None = Field(default=None, description="the mapper's progress")


class SessionList(BaseModel):
    sessions: list[SessionSummary]


class Deleted(BaseModel):
    id: str
    deleted: bool = True


class Repaired(BaseModel):
    """What ``repair_session`` did."""

    id: str
    repaired: bool = Field(description="False: the session was not damaged; nothing changed")
    rolled_back_to: int | None = Field(
        default=None, description="the intact earlier version restored (what later versions "
                                  "changed is lost)")
    dropped_frames: list[int] = Field(
        default_factory=list, description="views whose damaged image / depth was dropped")
    version: int = Field(description="the session's version now (a repair is a state change)")
    message: str = Field(description="what was done, in words")


class Health(BaseModel):
    status: Literal["ok"] = "ok"
    version: str
    sessions: int = Field(description="sessions held (damaged ones included)")
    damaged: int = Field(default=0, description="sessions held whose files do not check out")
    zenoh: bool
    uptime_s: float


# ---------------------------------------------------------------------------- Gaussians
class GaussianArrays(BaseModel):
    """The five parameter tensors (float32 or float64): means [N,3], log_scales [N,3]
    (log standard deviations), quats [N,4] (w, x, y, z), opacity_logits [N] (pre-sigmoid),
    sh [N,(d+1)^2,3] (DC first, d <= 3)."""

    model_config = ConfigDict(extra="forbid", strict=True,
                              json_schema_extra={RULES_KEY: ["gaussian-arrays"]})

    means: NDArray
    log_scales: NDArray
    quats: NDArray
    opacity_logits: NDArray
    sh: NDArray


class GaussiansIn(BaseModel):
    """Gaussians as a file (``ply``: Inria 3DGS PLY; ``splat``: antimatter15 32-byte
    records) in ``data``, or as ``arrays``."""

    model_config = ConfigDict(extra="forbid", strict=True, json_schema_extra=one_of([
        Form("GaussiansFile", ("format", "data"), ("arrays",),
             {"format": {"type": "string", "enum": ["ply", "splat"]}}),
        Form("GaussiansArrays", ("format", "arrays"), ("data",),
             {"format": {"type": "string", "const": "arrays"}}),
    ], rules=("gaussians-file",)))

    format: Literal["ply", "splat", "arrays"]
    data: B64Bytes | None = Field(default=None, description="file bytes (ply / splat)")
    arrays: GaussianArrays | None = Field(default=None, description="tensors (arrays)")

    @model_validator(mode="after")
    def _consistent(self) -> GaussiansIn:
        if self.format == "arrays":
            if self.arrays is None or self.data is not None:
                raise ValueError("format 'arrays' takes arrays and no data")
        elif self.data is None or self.arrays is not None:
            raise ValueError(f"format {self.format!r} takes data (the file bytes) and no arrays")
        return self


class GaussiansOut(BaseModel):
    """A session's current (published) Gaussians as float32 arrays, with the session
    ``version`` they belong to and the mapper's training steps they hold."""

    arrays: GaussianArrays
    count: int
    sh_degree: int
    version: int
    mapper_steps: int = Field(description="training steps of the mapper this map holds")

    def to_numpy(self) -> dict[str, np.ndarray]:
        """The five parameter arrays (means, log_scales, quats, opacity_logits, sh)."""
        return {k: getattr(self.arrays, k).to_numpy() for k in FIELD_NAMES}


# ---------------------------------------------------------------------------- observations
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
    depth: NDArray | None = Field(default=None, json_schema_extra=_narrowed({
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


def _frames_in(value: Any) -> Any:
    """Initial frames given as :class:`ObservationIn` objects, as the fields they set."""
    if isinstance(value, list | tuple):
        return [{k: getattr(o, k) for k in o.model_fields_set}
                if isinstance(o, ObservationIn) and not isinstance(o, InitialFrame) else o
                for o in value]
    return value


class ObservationsIn(BaseModel):
    model_config = _STRICT

    observations: list[ObservationIn] = Field(min_length=1, max_length=MAX_OBSERVATIONS_WIRE)


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


# ---------------------------------------------------------------------------- pool
class PoolIn(BaseModel):
    """Candidate poses (camera-to-world), optionally with client-chosen ``ids``; without
    ids the server numbers them on from the session's counter. The poses are validated as
    one array (:data:`~agilegs.schemas.geometry.PoseList`)."""

    model_config = ConfigDict(extra="forbid", strict=True,
                              json_schema_extra={RULES_KEY: ["same-length"]})

    poses: PoseList = Field(max_length=MAX_POOL_WIRE)
    ids: list[Id] | None = Field(default=None, description="one id per pose, unique",
                                 json_schema_extra=_UNIQUE)

    @model_validator(mode="after")
    def _ids(self) -> PoolIn:
        if self.ids is not None:
            if len(self.ids) != len(self.poses):
                raise ValueError(f"ids has {len(self.ids)} entries for {len(self.poses)} poses")
            _unique(self.ids, "ids")
        return self

    @classmethod
    def from_numpy(cls, poses: Any, ids: list[int] | None = None, validate: bool = True) -> PoolIn:
        """A pool from camera-to-world matrices [D, 4, 4]."""
        m = np.asarray(poses, dtype=np.float64)
        if m.ndim != 3 or m.shape[1:] != (4, 4):
            raise ValueError(f"poses must have shape [D, 4, 4], got {list(m.shape)}")
        if validate:  # checked as one array (PoseList)
            return cls.model_validate({"poses": [{"matrix": r} for r in m.tolist()], "ids": ids})
        return cls.model_construct(poses=trusted_poses(m), ids=ids)


class Candidate(BaseModel):
    id: int
    pose: Pose


class PoolOut(BaseModel):
    candidates: list[Candidate]
    version: int

    def ids(self) -> list[int]:
        return [c.id for c in self.candidates]

    def matrices(self) -> np.ndarray:
        """Candidate poses [D, 4, 4]."""
        if not self.candidates:
            return np.zeros((0, 4, 4))
        return np.stack([c.pose.to_matrix() for c in self.candidates])


# ---------------------------------------------------------------------------- selection
class SelectRequest(BaseModel):
    """Choose the next view among the pool. Unset fields take the session's defaults.

    Embodied mode (``embodied_k``) restricts the choice to the K candidates nearest the
    current view: ``current_id`` (a candidate), ``current_pose``, or else the last acquired
    view. ``pool`` replaces the pool first (as set_pool does, persisted); a pool that is the
    session's pool as it is (the same poses in the same order, the same ids or none) leaves
    it, its ids and the version unchanged. ``commit``
    acquires the chosen candidate (as a commit does) in the same step. A selection without
    commit changes nothing.
    """

    model_config = ConfigDict(extra="forbid", strict=True, json_schema_extra={
        "not": {"required": ["current_id", "current_pose"], "properties": {
            "current_id": {"type": "integer"}, "current_pose": {"type": "object"}}}})

    method: Method | None = None
    shortlist_size: ShortlistSize | None = None
    shortlist: ShortlistStrategy | None = None
    embodied_k: EmbodiedK | None = None
    seed: Seed | None = None
    fields: list[FieldName] | None = Field(default=None, json_schema_extra=_UNIQUE)
    config: SelectConfigPatch | None = Field(
        default=None, description="SelectConfig fields, merged over the session's config"
    )
    current_id: Id | None = Field(default=None, description="the current view, a candidate id")
    current_pose: Pose | None = Field(default=None, description="the current view's pose")
    pool: PoolIn | None = Field(default=None, description="replace the pool before selecting")
    commit: bool = Field(default=False, description="acquire the chosen candidate")

    @model_validator(mode="after")
    def _current(self) -> SelectRequest:
        if self.current_id is not None and self.current_pose is not None:
            raise ValueError("give current_id or current_pose, not both")
        _unique(self.fields, "fields")
        return self


class ScoredCandidate(BaseModel):
    id: int
    score: float | None = Field(description="the method's score where it computed one")


class SelectResponse(BaseModel):
    """A decision: the chosen candidate, the shortlist with scores, the anchor, timings.

    ``latency_ms`` is the selection core's own breakdown (anchor, scoring, leverage,
    rerank, total); ``core_ms`` adds the session work around it (pose conversion, id
    mapping, and the commit when asked); ``server_ms`` runs from the request's arrival to
    the response being ready to encode. Transport overhead = round trip - ``latency_ms.total``.
    """

    session: str
    method: str
    chosen: Candidate
    shortlist: list[ScoredCandidate]
    anchor: Pose | None = Field(description="anchor pose (agile, agile_plus)")
    scores: list[ScoredCandidate] = Field(description="every score the method computed")
    eligible: list[int] = Field(description="candidate ids that could be chosen")
    psi_trace: list[float]
    latency_ms: dict[str, float]
    core_ms: float
    server_ms: float | None = None
    committed: View | None = Field(description="the acquired view when commit was asked")
    version: int
    time: float = Field(description="unix time (s) of the decision")


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


class InformationOut(BaseModel):
    """Ĥ per parameter block (float32), with its summary."""

    fields: dict[str, NDArray]
    summary: InformationSummary
    version: int

    def arrays(self) -> dict[str, np.ndarray]:
        """Ĥ per parameter block as numpy arrays."""
        return {k: v.to_numpy() for k, v in self.fields.items()}


SessionCreate.model_rebuild()
