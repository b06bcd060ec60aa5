"""Request builders shared by every client (no I/O): each returns the operation, the session
and the request model; numpy inputs are turned into wire models here."""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, ParamSpec, TypeVar, cast

import numpy as np
from pydantic import BaseModel
from pydantic import ValidationError as PydanticValidationError

from agilegs import schemas as m
from agilegs.schemas import (
    OPERATIONS,
    Bounds,
    DecisionsRequest,
    Intrinsics,
    NDArray,
    Operation,
    Pose,
)
from agilegs.schemas.codec import GAUSSIAN_FILE_TYPES
from agilegs.schemas.config import SelectConfigPatch
from agilegs.schemas.geometry import trusted_poses
from agilegs.schemas.requests import new_request_id
from agilegs.schemas.views import InitialFrame

from .errors import ValidationError

__all__ = ["Call", "PoseLike"]

P = ParamSpec("P")
R = TypeVar("R")


def checked(fn: Callable[P, R]) -> Callable[P, R]:
    """Refuse bad arguments before sending, with the 422 the server would give."""

    @functools.wraps(fn)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        try:
            return fn(*args, **kwargs)
        except PydanticValidationError as exc:
            e = exc.errors(include_url=False, include_input=False)[0]
            field = "body" + "".join(f"[{p}]" if isinstance(p, int) else f".{p}"
                                     for p in e["loc"])
            raise ValidationError(422, "invalid", f"{field}: {e['msg']}", field) from exc
        except ValueError as exc:
            raise ValidationError(422, "invalid", str(exc), None) from exc

    return wrapper

PoseLike = Pose | np.ndarray | Sequence[Sequence[float]]


@dataclass(frozen=True)
class Call:
    """One request: which operation, on which session, with which body."""

    op: Operation
    session: str | None = None
    body: BaseModel | None = None
    params: dict[str, str] | None = None  # query parameters (HTTP) / selector (Zenoh)
    file: str | None = None  # answered as this file (get_gaussians: ply / splat), as bytes
    request_id: str | None = None  # a write's request id: its retries apply it once

    def with_request_id(self) -> Call:
        """This call with a fresh request id when it is a write without one
        (:mod:`agilegs.schemas.requests`): every retry of it then carries the same id."""
        if self.op.http_method == "GET" or self.request_id is not None:
            return self
        return replace(self, request_id=new_request_id())


def call(name: str, session: str | None = None, body: BaseModel | None = None) -> Call:
    return Call(OPERATIONS[name], session, body)


@checked
def to_pose(p: PoseLike) -> Pose:
    if isinstance(p, Pose):
        return p
    return Pose.from_matrix(np.asarray(p, dtype=np.float64))


@checked
def to_pool(poses: m.PoolIn | np.ndarray | Sequence[PoseLike], ids: Sequence[int] | None
            ) -> m.PoolIn:
    if isinstance(poses, m.PoolIn):
        return poses
    if isinstance(poses, np.ndarray):
        if poses.ndim != 3 or poses.shape[1:] != (4, 4):
            raise ValueError(f"poses must have shape [D, 4, 4], got {list(poses.shape)}")
        plist: list[Pose] = trusted_poses(poses)  # the server validates them as one array
    else:
        plist = [to_pose(p) for p in poses]
    return m.PoolIn.model_construct(poses=plist, ids=list(ids) if ids is not None else None)


@checked
def to_gaussians(g: m.GaussiansIn | str | Path | Mapping[str, Any]) -> m.GaussiansIn:
    """A GaussiansIn from a model, a ``.ply`` / ``.splat`` path, or a dict of arrays."""
    if isinstance(g, m.GaussiansIn):
        return g
    if isinstance(g, str | Path):
        path = Path(g)
        fmt = path.suffix.lower().lstrip(".")
        if fmt not in ("ply", "splat"):
            raise ValueError(f"{path}: expected a .ply or .splat file")
        return m.GaussiansIn(format=fmt, data=path.read_bytes())  # type: ignore[arg-type]
    arrays = {k: NDArray.from_numpy(np.asarray(v, dtype=np.float32)) for k, v in g.items()}
    return m.GaussiansIn(format="arrays", arrays=m.GaussianArrays(**arrays))


@checked
def gaussians_file(session: str, path: str | Path) -> Call:
    """``get_gaussians`` answered as the file ``path``'s suffix names (.ply / .splat)."""
    fmt = Path(path).suffix.lower().lstrip(".")
    if fmt not in GAUSSIAN_FILE_TYPES:
        raise ValueError(f"{path}: the file name must end in .ply (Inria 3DGS) or .splat")
    return Call(OPERATIONS["get_gaussians"], session, None, file=fmt)


def write_file(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temporary name (a reader never sees half of it)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.part")
    try:
        tmp.write_bytes(data)
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


@checked
def to_observation(o: m.ObservationIn | Mapping[str, Any]) -> m.ObservationIn:
    if isinstance(o, m.ObservationIn):
        return o
    return m.ObservationIn.from_numpy(**dict(o))


@checked
def to_frame(o: m.ObservationIn | Mapping[str, Any]) -> InitialFrame:
    """An initial frame of a session (an observation at a pose)."""
    if isinstance(o, InitialFrame):
        return o
    if isinstance(o, m.ObservationIn):
        return InitialFrame.model_validate({k: getattr(o, k) for k in o.model_fields_set})
    return cast(InitialFrame, InitialFrame.from_numpy(**dict(o)))


@checked
def create_session(
    intrinsics: Intrinsics | Mapping[str, Any],
    *,
    id: str | None = None,
    bounds: Bounds | Mapping[str, Any] | None = None,
    gaussians: m.GaussiansIn | str | Path | Mapping[str, Any] | None = None,
    frames: Sequence[m.ObservationIn | Mapping[str, Any]] = (),
    init_gaussians: int = 1000,
    seed: int = 0,
    pool: m.PoolIn | np.ndarray | Sequence[PoseLike] | None = None,
    defaults: m.SelectDefaults | Mapping[str, Any] | None = None,
    information: m.InformationConfig | Mapping[str, Any] | None = None,
    mapper: m.MapperOptions | Mapping[str, Any] | None = None,
    instance: str | None = None,
) -> Call:
    body = m.SessionCreate(
        id=id,
        intrinsics=Intrinsics.model_validate(intrinsics),
        bounds=Bounds.model_validate(bounds) if bounds is not None else None,
        gaussians=to_gaussians(gaussians) if gaussians is not None else None,
        frames=[to_frame(f) for f in frames],
        init_gaussians=init_gaussians,
        seed=seed,
        pool=to_pool(pool, None) if pool is not None else None,
        defaults=m.SelectDefaults.model_validate(defaults or {}),
        information=m.InformationConfig.model_validate(information or {}),
        mapper=m.MapperOptions.model_validate(mapper or {}),
    )
    out = call("create_session", None, body)
    return out if instance is None else replace(out, params={"instance": instance})


@checked
def select(
    session: str,
    *,
    method: str | None = None,
    shortlist_size: int | None = None,
    shortlist: str | None = None,
    embodied_k: int | None = None,
    seed: int | None = None,
    fields: Sequence[str] | None = None,
    config: Mapping[str, Any] | None = None,
    current_id: int | None = None,
    current_pose: PoseLike | None = None,
    pool: m.PoolIn | np.ndarray | Sequence[PoseLike] | None = None,
    commit: bool = False,
    targets: np.ndarray | Sequence[PoseLike] | None = None,
) -> Call:
    body = m.SelectRequest.model_construct(
        method=method,
        shortlist_size=shortlist_size,
        shortlist=shortlist,
        embodied_k=embodied_k,
        seed=seed,
        fields=list(fields) if fields is not None else None,
        config=SelectConfigPatch.model_validate(dict(config)) if config is not None else None,
        current_id=current_id,
        current_pose=to_pose(current_pose) if current_pose is not None else None,
        pool=to_pool(pool, None) if pool is not None else None,
        targets=to_pool(targets, None).poses if targets is not None else None,
        commit=commit,
    )
    return call("select", session, body)


@checked
def commit(session: str, candidate_id: int | None = None, *, pose: PoseLike | None = None,
           keep_in_pool: bool = False) -> Call:
    body = m.CommitRequest.model_construct(
        candidate_id=candidate_id, pose=to_pose(pose) if pose is not None else None,
        keep_in_pool=keep_in_pool,
    )
    return call("commit", session, body)


@checked
def add_observations(session: str, observations: m.ObservationIn | Mapping[str, Any]
                     | Sequence[m.ObservationIn | Mapping[str, Any]]) -> Call:
    if isinstance(observations, m.ObservationIn | Mapping):
        observations = [observations]
    body = m.ObservationsIn.model_construct(
        observations=[to_observation(o) for o in observations])
    return call("add_observations", session, body)


@checked
def get_frames(session: str, view_id: int | None = None, *, depth: bool = True) -> Call:
    return call("get_frames", session, m.FramesRequest(view_id=view_id, depth=depth))


@checked
def get_decisions(session: str, *, after: int = 0, wait: float = 0.0, limit: int = 100) -> Call:
    return call("get_decisions", session, DecisionsRequest(after=after, wait=wait, limit=limit))


def query_params(body: BaseModel) -> dict[str, str]:
    """A request model's fields as HTTP query parameters (an operation with ``query``)."""
    return {k: str(v).lower() if isinstance(v, bool) else str(v)
            for k, v in body.model_dump(mode="json").items() if v is not None}
