"""The one selection / session core that both transports (HTTP and Zenoh) call.

:class:`ServiceCore` holds the sessions and dispatches every operation of
:data:`agilegs.schemas.ops.OPERATIONS` through :meth:`ServiceCore.call`: the transports only
decode a body into Python data, call it (in a worker thread), and encode what it returns or
the :class:`ServiceError` it raises.

:class:`SessionCore` holds one session: its Gaussians, Ĥ, acquired views, candidate pool
and defaults, as an immutable :class:`~agilegs.service.store.SessionRecord`. Every change
follows the same steps, under the session's lock: validate everything (a :class:`ServiceError`
leaves the session as it was), build a new record, persist it (the store writes, fsyncs and
renames), then swap it in; only then is the change acknowledged. Reads take the current
record without the lock (records are never mutated), so they never wait behind a selection.

The maths lives in :mod:`agilegs.service.nbv` and is reached through :class:`MathBackend`.
The mapper (:mod:`agilegs.service.trainer`, started by :meth:`ServiceCore.load` when the
``mapper`` setting is on) trains each session's Gaussians from its images in a background
thread and publishes them through :meth:`SessionCore.replace_map`.
"""

from __future__ import annotations

import hashlib
import io
import logging
import math
import re
import threading
import time
import uuid
from collections.abc import Callable, Iterable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
from pydantic import BaseModel, ValidationError
from torch import Tensor

from agilegs.schemas import models as m
from agilegs.schemas.errors import ErrorBody, ErrorInfo, ErrorItem
from agilegs.schemas.geometry import Intrinsics as WireIntrinsics
from agilegs.schemas.geometry import Pose
from agilegs.schemas.ops import OPERATIONS

from .nbv.camera import Camera, Intrinsics
from .nbv.gaussians import FIELD_NAMES, GaussianMap
from .settings import Settings
from .store import SessionRecord, SessionStore, ViewRecord

__all__ = [
    "MathBackend",
    "NbvBackend",
    "ServiceCore",
    "ServiceError",
    "SessionCore",
    "validation_error",
]

log = logging.getLogger(__name__)

_SESSION_RE = re.compile(m.SESSION_ID_PATTERN)


# ============================================================================ errors
class ServiceError(Exception):
    """A request the service refuses: HTTP status, stable code, message, and the field."""

    def __init__(
        self,
        status: int,
        code: str,
        message: str,
        field: str | None = None,
        errors: list[ErrorItem] | None = None,
    ) -> None:
        super().__init__(message)
        self.status = status
        self.code = code
        self.message = message
        self.field = field
        self.errors = errors if errors is not None else [ErrorItem(field=field, message=message)]

    def body(self) -> ErrorBody:
        return ErrorBody(
            error=ErrorInfo(
                status=self.status,
                code=self.code,
                message=self.message,
                field=self.field,
                errors=self.errors,
            )
        )

    def __repr__(self) -> str:
        return f"ServiceError({self.status}, {self.code!r}, {self.message!r}, field={self.field!r})"


def invalid(field: str | None, message: str) -> ServiceError:
    return ServiceError(422, "invalid", message, field)


def not_found(field: str | None, message: str) -> ServiceError:
    return ServiceError(404, "not_found", message, field)


def conflict(field: str | None, message: str, code: str = "conflict") -> ServiceError:
    return ServiceError(409, code, message, field)


def too_large(field: str | None, message: str) -> ServiceError:
    return ServiceError(413, "limit_exceeded", message, field)


def too_many(field: str | None, message: str) -> ServiceError:
    return ServiceError(429, "too_many", message, field)


def field_path(prefix: str, loc: Iterable[int | str]) -> str:
    """``body`` + ``('poses', 3, 'matrix')`` -> ``body.poses[3].matrix``."""
    out = prefix
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += f".{part}" if out else str(part)
    return out


def validation_error(exc: ValidationError, prefix: str = "body") -> ServiceError:
    """A pydantic ValidationError as a 422 naming every field."""
    items = []
    for e in exc.errors(include_url=False, include_input=False):
        msg = str(e.get("msg", "invalid"))
        for lead in ("Value error, ", "Assertion failed, "):
            if msg.startswith(lead):
                msg = msg[len(lead):]
        items.append(ErrorItem(field=field_path(prefix, e.get("loc", ())), message=msg))
    first = items[0] if items else ErrorItem(field=prefix, message="invalid")
    more = f" (and {len(items) - 1} more)" if len(items) > 1 else ""
    return ServiceError(422, "invalid", f"{first.field}: {first.message}{more}", first.field,
                        items)


# ============================================================================ maths backend
class MathBackend(Protocol):
    """The maths the core calls (tensors in, tensors out)."""

    def init_information(self, gmap: GaussianMap, lam: float) -> dict[str, Tensor]: ...

    def view_information(
        self, gmap: GaussianMap, c2w: Tensor, intrinsics: Intrinsics
    ) -> dict[str, Tensor]: ...

    def accumulate(
        self, h_acc: Mapping[str, Tensor], h_view: Mapping[str, Tensor]
    ) -> dict[str, Tensor]: ...

    def make_config(self, options: dict[str, Any]) -> Any: ...

    def select(
        self,
        method: str,
        gmap: GaussianMap,
        h_acc: Mapping[str, Tensor],
        candidates: Tensor,
        intrinsics: Intrinsics,
        *,
        config: Any,
        acquired: Tensor | None,
        current: int | None,
        current_pose: Tensor | None,
        state: dict[str, Any] | None,
    ) -> Any: ...

    def load_gaussians(self, path: Path) -> GaussianMap: ...


class NbvBackend:
    """:class:`MathBackend` over :mod:`agilegs.service.nbv`."""

    def init_information(self, gmap: GaussianMap, lam: float) -> dict[str, Tensor]:
        from .nbv.information import init_information

        return init_information(gmap, lam)

    def view_information(
        self, gmap: GaussianMap, c2w: Tensor, intrinsics: Intrinsics
    ) -> dict[str, Tensor]:
        from .nbv.information import fisher_diag

        if gmap.num_gaussians == 0:
            return {k: torch.zeros_like(v) for k, v in gmap.items()}
        with torch.no_grad():
            return fisher_diag(gmap.detach(), Camera(c2w=c2w.to(gmap.dtype), intrinsics=intrinsics))

    def accumulate(
        self, h_acc: Mapping[str, Tensor], h_view: Mapping[str, Tensor]
    ) -> dict[str, Tensor]:
        from .nbv.information import accumulate_information

        return accumulate_information(h_acc, h_view)

    def make_config(self, options: dict[str, Any]) -> Any:
        """A validated ``SelectConfig`` from plain options (nested dicts for anchor / scoring);
        ValueError naming the option."""
        from .nbv.selectors import AnchorConfig, ScoringConfig, SelectConfig

        return _build_dataclass(
            SelectConfig, options, "config", {"anchor": AnchorConfig, "scoring": ScoringConfig}
        )

    def select(
        self,
        method: str,
        gmap: GaussianMap,
        h_acc: Mapping[str, Tensor],
        candidates: Tensor,
        intrinsics: Intrinsics,
        *,
        config: Any,
        acquired: Tensor | None,
        current: int | None,
        current_pose: Tensor | None,
        state: dict[str, Any] | None,
    ) -> Any:
        from .nbv.selectors import select

        return select(method, gmap, h_acc, candidates, intrinsics, config=config,
                      acquired=acquired, current=current, current_pose=current_pose, state=state)

    def load_gaussians(self, path: Path) -> GaussianMap:
        return GaussianMap.load(path)


def _build_dataclass(cls: type, options: Any, where: str, nested: dict[str, type]) -> Any:
    """``cls(**options)`` with every value type-checked by pydantic; ValueError naming it."""
    import dataclasses

    from pydantic import ConfigDict, TypeAdapter  # noqa: F401 (TypeAdapter used below)

    if not isinstance(options, dict):
        raise ValueError(f"{where}: must be an object, got {type(options).__name__}")
    known = {f.name: f for f in dataclasses.fields(cls)}
    kwargs: dict[str, Any] = {}
    for key, value in options.items():
        if key not in known:
            raise ValueError(f"{where}.{key}: unknown option (known: {sorted(known)})")
        if key in nested:
            kwargs[key] = _build_dataclass(nested[key], value, f"{where}.{key}", {})
            continue
        adapter = _ADAPTERS.get((cls, key))
        if adapter is None:
            hint = _resolved_hints(cls)[key]
            adapter = TypeAdapter(hint, config=ConfigDict(arbitrary_types_allowed=True))
            _ADAPTERS[(cls, key)] = adapter
        try:
            kwargs[key] = adapter.validate_python(value, strict=False)
        except ValidationError as exc:
            msg = exc.errors(include_url=False)[0]["msg"]
            raise ValueError(f"{where}.{key}: {msg}") from None
        if isinstance(kwargs[key], float) and not math.isfinite(kwargs[key]):
            raise ValueError(f"{where}.{key}: must be finite")
    try:
        obj = cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{where}: {exc}") from None
    if hasattr(obj, "validate"):
        obj.validate()  # its messages name the option ("config.seed ...", "anchor.steps ...")
    return obj


_HINTS: dict[type, dict[str, Any]] = {}
_ADAPTERS: dict[tuple[type, str], Any] = {}


def _resolved_hints(cls: type) -> dict[str, Any]:
    if cls not in _HINTS:
        import sys
        import typing

        _HINTS[cls] = typing.get_type_hints(cls, vars(sys.modules[cls.__module__]))
    return _HINTS[cls]


# ============================================================================ conversions
def nbv_intrinsics(d: Mapping[str, Any]) -> Intrinsics:
    return Intrinsics(
        fx=float(d["fx"]), fy=float(d["fy"]), cx=float(d["cx"]), cy=float(d["cy"]),
        width=int(d["width"]), height=int(d["height"]),
    )


def pose_out(matrix: np.ndarray | Tensor) -> Pose:
    a = matrix.detach().cpu().numpy() if isinstance(matrix, Tensor) else np.asarray(matrix)
    return Pose.from_matrix(a.astype(np.float64), validate=False)


def poses_array(poses: list[Pose]) -> np.ndarray:
    """Camera-to-world matrices [D, 4, 4] (float64) of validated wire poses."""
    if not poses:
        return np.zeros((0, 4, 4))
    if all(p.matrix is not None for p in poses):  # the common case, in one conversion
        return np.asarray([p.matrix for p in poses], dtype=np.float64)
    return np.stack([p.to_matrix() for p in poses])


def _finite_float(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def information_summary(h: Mapping[str, Tensor]) -> m.InformationSummary:
    digest = hashlib.sha256()
    fields: dict[str, m.FieldSummary] = {}
    for name in FIELD_NAMES:
        if name not in h:
            continue
        t = h[name].detach().cpu().to(torch.float32).contiguous()
        digest.update(name.encode())
        digest.update(t.numpy().astype("<f4").tobytes())
        fields[name] = m.FieldSummary(
            shape=list(t.shape),
            sum=float(t.sum(dtype=torch.float64)),
            min=float(t.min()) if t.numel() else None,
            max=float(t.max()) if t.numel() else None,
        )
    return m.InformationSummary(fields=fields, digest=digest.hexdigest())


def _check_finite_tensor(t: Tensor, field: str) -> None:
    if not bool(torch.isfinite(t).all()):
        raise invalid(field, "contains NaN or infinite values")


def gaussians_from_arrays(a: m.GaussianArrays, field: str) -> GaussianMap:
    tensors: dict[str, Tensor] = {}
    for name in FIELD_NAMES:
        arr: m.NDArray = getattr(a, name)
        if arr.dtype not in ("float32", "float64"):
            raise invalid(f"{field}.{name}.dtype", "must be float32 or float64")
        t = torch.from_numpy(arr.to_numpy().astype(np.float32))
        _check_finite_tensor(t, f"{field}.{name}")
        tensors[name] = t
    try:
        return GaussianMap(**tensors)
    except ValueError as exc:
        raise invalid(field, str(exc)) from None


def random_gaussians(bounds: m.Bounds, count: int, seed: int) -> GaussianMap:
    """``count`` grey, faint, isotropic Gaussians uniformly inside ``bounds`` (a prior)."""
    lo = torch.tensor(bounds.min, dtype=torch.float64)
    hi = torch.tensor(bounds.max, dtype=torch.float64)
    if count == 0:
        return _empty_map()
    g = torch.Generator().manual_seed(seed)
    pts = lo + (hi - lo) * torch.rand(count, 3, generator=g, dtype=torch.float64)
    volume = float(torch.prod(hi - lo))
    scale = 0.5 * (volume / count) ** (1 / 3)
    colors = torch.full((count, 3), 0.5, dtype=torch.float64)
    return GaussianMap.from_points(pts.float(), colors.float(), scale=scale, opacity=0.1)


def _empty_map() -> GaussianMap:
    z = torch.zeros
    return GaussianMap(means=z(0, 3), log_scales=z(0, 3), quats=z(0, 4), opacity_logits=z(0),
                       sh=z(0, 1, 3))


@dataclass
class _Frame:
    """A validated observation, ready to become (or attach to) a view."""

    index: int
    obs: m.ObservationIn
    intrinsics: dict[str, Any] | None
    image_bytes: bytes | None = None
    image_ext: str | None = None
    image_rgb: np.ndarray | None = None  # decoded, for depth initialisation
    depth: np.ndarray | None = None  # [H, W] float32, scene units (0: missing)
    pose: np.ndarray | None = None


# ============================================================================ per session
class SessionCore:
    """One session's state and operations (see the module docstring)."""

    def __init__(
        self, record: SessionRecord, core: ServiceCore
    ) -> None:
        self.record = record
        self.core = core
        self.lock = threading.Lock()
        self.closed = False
        self.mapper: Any = None  # the mapper plugs in through on_observation
        self._summary: tuple[int, m.InformationSummary] | None = None  # (version, summary)

    # ------------------------------------------------------------------ helpers
    @property
    def id(self) -> str:
        return self.record.id

    @property
    def settings(self) -> Settings:
        return self.core.settings

    @property
    def backend(self) -> MathBackend:
        return self.core.backend

    def _check_open(self) -> None:
        if self.closed:
            raise not_found("session", f"session {self.id!r} was deleted")

    def _intrinsics(self, rec: SessionRecord | None = None) -> Intrinsics:
        return nbv_intrinsics((rec or self.record).intrinsics)

    def _commit(self, new: SessionRecord, dirty: Iterable[str], blobs: dict[str, bytes] | None
                = None) -> SessionRecord:
        """Persist ``new`` (version bumped by the caller) and swap it in."""
        saved = self.core.store.save(new, dirty, blobs)
        self.record = saved
        return saved

    def _bump(self, rec: SessionRecord, **changes: Any) -> SessionRecord:
        return replace(rec, version=rec.version + 1, updated_at=time.time(), **changes)

    def _view_info(self, gmap: GaussianMap, pose: np.ndarray, rec: SessionRecord
                   ) -> dict[str, Tensor]:
        c2w = torch.from_numpy(pose).to(gmap.dtype)
        return self.backend.view_information(gmap, c2w, self._intrinsics(rec))

    def _accumulate_views(self, h: dict[str, Tensor], gmap: GaussianMap,
                          poses: Iterable[np.ndarray], rec: SessionRecord) -> dict[str, Tensor]:
        for pose in poses:
            h = self.backend.accumulate(h, self._view_info(gmap, pose, rec))
        return h

    def _recompute_information(self, gmap: GaussianMap, rec: SessionRecord) -> dict[str, Tensor]:
        h = self.backend.init_information(gmap, float(rec.information_config["lambda"]))
        return self._accumulate_views(h, gmap, (v.pose for v in rec.views), rec)

    def _pool_index(self, rec: SessionRecord, cid: int, field: str) -> int:
        hits = np.nonzero(rec.pool_ids == cid)[0]
        if hits.size == 0:
            raise not_found(field, f"candidate {cid} is not in the pool")
        return int(hits[0])

    def _without(self, rec: SessionRecord, index: int) -> dict[str, Any]:
        keep = np.ones(len(rec.pool_ids), dtype=bool)
        keep[index] = False
        return {"pool_ids": rec.pool_ids[keep], "pool_poses": rec.pool_poses[keep]}

    # ------------------------------------------------------------------ read
    def information_summary(self, rec: SessionRecord) -> m.InformationSummary:
        """Ĥ's summary and digest, computed once per version."""
        cached = self._summary
        if cached is not None and cached[0] == rec.version:
            return cached[1]
        summary = information_summary(rec.h_acc)
        self._summary = (rec.version, summary)
        return summary

    def info(self) -> m.SessionInfo:
        rec = self.record
        g = rec.gmap
        means_min = means_max = None
        if len(g):
            means_min = g.means.detach().amin(0).tolist()
            means_max = g.means.detach().amax(0).tolist()
        return m.SessionInfo(
            id=rec.id,
            created_at=rec.created_at,
            updated_at=rec.updated_at,
            version=rec.version,
            intrinsics=WireIntrinsics(**rec.intrinsics),
            bounds=m.Bounds(**rec.bounds) if rec.bounds else None,
            defaults=m.SelectDefaults(**rec.defaults),
            information_config=m.InformationConfig(**rec.information_config),
            gaussians=m.GaussiansSummary(count=len(g), sh_degree=g.sh_degree, means_min=means_min,
                                         means_max=means_max),
            information=self.information_summary(rec),
            pool_size=len(rec.pool_ids),
            next_candidate_id=rec.next_candidate_id,
            num_views=len(rec.views),
            last_view_id=rec.views[-1].id if rec.views else None,
            mapper=self.mapper_status(rec),
        )

    def mapper_status(self, rec: SessionRecord | None = None) -> m.MapperStatus:
        """The mapper's progress as of ``rec`` (default: the current record); state ``off``
        when the mapper does not run for this session."""
        from .trainer import SessionTrainer, mapper_status

        rec = rec or self.record
        st = self.mapper
        if isinstance(st, SessionTrainer):
            return st.status(rec)
        return mapper_status(rec, self.settings.mapper_steps_per_view)

    def get_gaussians(self) -> m.GaussiansOut:
        """The published Gaussians as float32 arrays."""
        rec = self.record
        g = rec.gmap
        arrays = m.GaussianArrays(**{
            k: m.NDArray.from_numpy(v.detach().cpu().numpy().astype("<f4")) for k, v in g.items()
        })
        steps = int((rec.mapper or {}).get("steps", 0))
        return m.GaussiansOut(arrays=arrays, count=len(g), sh_degree=g.sh_degree,
                              version=rec.version, mapper_steps=steps)

    def summary(self) -> m.SessionSummary:
        rec = self.record
        return m.SessionSummary(id=rec.id, version=rec.version, num_gaussians=len(rec.gmap),
                                pool_size=len(rec.pool_ids), num_views=len(rec.views),
                                updated_at=rec.updated_at)

    def get_pool(self) -> m.PoolOut:
        rec = self.record
        return _pool_out(rec)

    def list_views(self) -> m.ViewsOut:
        rec = self.record
        return m.ViewsOut(views=[_view_out(v) for v in rec.views], version=rec.version)

    def get_information(self) -> m.InformationOut:
        rec = self.record
        fields = {k: m.NDArray.from_numpy(v.detach().cpu().numpy().astype("<f4"))
                  for k, v in rec.h_acc.items()}
        return m.InformationOut(fields=fields, summary=self.information_summary(rec),
                                version=rec.version)

    def view_image(self, view_id: int) -> np.ndarray | None:
        """The stored image of a view as RGB [H, W, 3] (uint8 or float32), or None."""
        v = self._find_view(self.record, view_id)
        if v.image_file is None:
            return None
        data = self.core.store.read_blob(self.id, v.image_file)
        if v.image_encoding == "raw":
            return np.load(io.BytesIO(data), allow_pickle=False)
        from PIL import Image

        with Image.open(io.BytesIO(data)) as img:
            return np.asarray(img.convert("RGB"))

    def view_depth(self, view_id: int) -> np.ndarray | None:
        """The stored depth of a view [H, W] float32 in scene units (0: missing), or None."""
        v = self._find_view(self.record, view_id)
        if v.depth_file is None:
            return None
        return np.load(io.BytesIO(self.core.store.read_blob(self.id, v.depth_file)),
                       allow_pickle=False)

    @staticmethod
    def _find_view(rec: SessionRecord, view_id: int, field: str = "view_id") -> ViewRecord:
        for v in rec.views:
            if v.id == view_id:
                return v
        raise not_found(field, f"view {view_id} does not exist")

    # ------------------------------------------------------------------ Gaussians
    def set_gaussians(self, req: m.GaussiansIn) -> m.SessionInfo:
        gmap = self.core.parse_gaussians(req, "body")
        with self.lock:
            self._check_open()
            self.replace_map(gmap)
        return self.info()

    def replace_map(self, gmap: GaussianMap, *, src: Tensor | None = None,
                    mapper_progress: Mapping[str, Any] | None = None) -> SessionRecord:
        """Swap in a new map (a trainer's push, or the mapper's update); the lock is held.

        Args:
            gmap: the new Gaussians [N_new].
            src: the mapper's update: LongTensor [N_new], new Gaussian j descends from the
                current map's Gaussian ``src[j]`` (-1: new). Ĥ then follows
                ``information.mapper_update``: ``carry`` (default) remaps it per Gaussian
                (:func:`~agilegs.service.mapper.remap_per_gaussian`; new Gaussians get λ),
                ``recompute`` recomputes it from every acquired view on the new map.
                None (a push): Ĥ is recomputed from every acquired view when the Gaussian
                count changes or ``information.recompute_on_map_change`` is set, else kept.
            mapper_progress: the mapper's progress to persist with the map (merged into
                the record's ``mapper`` state).
        """
        rec = self.record
        if len(gmap) > self.settings.max_gaussians:
            raise too_large("body", f"{len(gmap)} Gaussians exceed max_gaussians "
                                    f"({self.settings.max_gaussians})")
        cfg = rec.information_config
        if src is not None:
            if tuple(src.shape) != (len(gmap),):
                raise ValueError(f"src must have shape [{len(gmap)}], got {list(src.shape)}")
            if cfg.get("mapper_update", "carry") == "recompute":
                h = self._recompute_information(gmap, rec)
            else:
                h = self._carry_information(gmap, src, rec)
        elif len(gmap) != len(rec.gmap) or cfg.get("recompute_on_map_change", True):
            h = self._recompute_information(gmap, rec)
        else:
            h = rec.h_acc
        changes: dict[str, Any] = {}
        if mapper_progress is not None:
            changes["mapper"] = {**(rec.mapper or {}), **mapper_progress}
        new = self._bump(rec, gmap=gmap, h_acc=h, **changes)
        return self._commit(new, ("gaussians", "information"))

    def _carry_information(self, gmap: GaussianMap, src: Tensor, rec: SessionRecord
                           ) -> dict[str, Tensor]:
        """Ĥ of ``rec`` carried to ``gmap`` along ``src`` (new Gaussians: λ)."""
        from .mapper import remap_per_gaussian

        h = remap_per_gaussian(rec.h_acc, src, 0.0)
        new = src.to(torch.long) < 0
        if bool(new.any()):
            prior = self.backend.init_information(gmap, float(rec.information_config["lambda"]))
            for k in h:
                h[k][new] = prior[k][new].to(h[k].dtype)
        return h

    # ------------------------------------------------------------------ pool
    def set_pool(self, req: m.PoolIn) -> m.PoolOut:
        with self.lock:
            self._check_open()
            new = self._pool_changed(self.record, req, "body", replace_pool=True)
            return _pool_out(self._commit(new, ("pool",)))

    def extend_pool(self, req: m.PoolIn) -> m.PoolOut:
        with self.lock:
            self._check_open()
            new = self._pool_changed(self.record, req, "body", replace_pool=False)
            return _pool_out(self._commit(new, ("pool",)))

    def _pool_changed(self, rec: SessionRecord, req: m.PoolIn, field: str, *,
                      replace_pool: bool) -> SessionRecord:
        d = len(req.poses)
        base = 0 if replace_pool else len(rec.pool_ids)
        if base + d > self.settings.max_pool_size:
            raise too_large(f"{field}.poses", f"the pool would hold {base + d} candidates; "
                                              f"max_pool_size is {self.settings.max_pool_size}")
        poses = poses_array(req.poses)
        if req.ids is not None:
            ids = np.asarray(req.ids, dtype=np.int64)
            if not replace_pool and len(rec.pool_ids):
                clash = np.nonzero(np.isin(ids, rec.pool_ids))[0]
                if clash.size:
                    i = int(clash[0])
                    raise conflict(f"{field}.ids[{i}]", f"candidate {int(ids[i])} is already "
                                                        "in the pool")
            next_id = max(rec.next_candidate_id, int(ids.max()) + 1 if d else 0)
        else:
            ids = np.arange(rec.next_candidate_id, rec.next_candidate_id + d, dtype=np.int64)
            next_id = rec.next_candidate_id + d
        if not replace_pool:
            ids = np.concatenate([rec.pool_ids, ids])
            poses = np.concatenate([rec.pool_poses, poses]) if d else rec.pool_poses
        return self._bump(rec, pool_ids=ids, pool_poses=poses, next_candidate_id=next_id)

    # ------------------------------------------------------------------ views
    def commit(self, req: m.CommitRequest) -> m.View:
        with self.lock:
            self._check_open()
            rec = self.record
            self._check_view_room(rec, 1, "body")
            changes: dict[str, Any] = {}
            if req.candidate_id is not None:
                i = self._pool_index(rec, req.candidate_id, "body.candidate_id")
                pose = rec.pool_poses[i]
                if not req.keep_in_pool:
                    changes.update(self._without(rec, i))
            else:
                assert req.pose is not None
                pose = req.pose.to_matrix()
            view = ViewRecord(id=rec.next_view_id, pose=pose, candidate_id=req.candidate_id,
                              created_at=time.time())
            h = self.backend.accumulate(rec.h_acc, self._view_info(rec.gmap, pose, rec))
            new = self._bump(rec, views=rec.views + (view,), next_view_id=view.id + 1,
                             h_acc=h, **changes)
            self._commit(new, ("information", "pool") if changes else ("information",))
            return _view_out(view)

    def _check_view_room(self, rec: SessionRecord, n: int, field: str) -> None:
        if len(rec.views) + n > self.settings.max_views:
            raise too_many(field, f"the session would hold {len(rec.views) + n} views; "
                                  f"max_views is {self.settings.max_views}")

    def add_observations(self, req: m.ObservationsIn) -> m.ViewsOut:
        frames = [self.core.parse_frame(o, i, "body.observations", self.record.intrinsics)
                  for i, o in enumerate(req.observations)]
        with self.lock:
            self._check_open()
            new, blobs, touched = self._integrate(self.record, frames, "body.observations")
            pool_changed = len(new.pool_ids) != len(self.record.pool_ids)
            dirty = ["information"] + (["pool"] if pool_changed else [])
            saved = self._commit(new, dirty, blobs)
            self.on_observation(touched)
            return m.ViewsOut(views=[_view_out(v) for v in touched], version=saved.version)

    def _integrate(self, rec: SessionRecord, frames: list[_Frame], field: str
                   ) -> tuple[SessionRecord, dict[str, bytes], list[ViewRecord]]:
        """A record with ``frames`` added as views (or attached to views), Ĥ updated."""
        views = list(rec.views)
        pool_ids, pool_poses = rec.pool_ids, rec.pool_poses
        next_view = rec.next_view_id
        blobs: dict[str, bytes] = {}
        touched: list[ViewRecord] = []
        new_poses: list[np.ndarray] = []
        n_new = sum(1 for f in frames if f.obs.view_id is None)
        self._check_view_room(rec, n_new, field)
        for fr in frames:
            o = fr.obs
            where = f"{field}[{fr.index}]"
            if o.view_id is not None:
                pos = next((k for k, v in enumerate(views) if v.id == o.view_id), None)
                if pos is None:
                    raise not_found(f"{where}.view_id", f"view {o.view_id} does not exist")
                if views[pos].image_file is not None or views[pos].depth_file is not None:
                    raise conflict(f"{where}.view_id", f"view {o.view_id} already has a frame")
                view = views[pos]
            else:
                candidate = None
                if o.candidate_id is not None:
                    hits = np.nonzero(pool_ids == o.candidate_id)[0]
                    if hits.size == 0:
                        raise not_found(f"{where}.candidate_id",
                                        f"candidate {o.candidate_id} is not in the pool")
                    i = int(hits[0])
                    candidate = o.candidate_id
                    pose = o.pose.to_matrix() if o.pose is not None else pool_poses[i]
                    keep = np.ones(len(pool_ids), dtype=bool)
                    keep[i] = False
                    pool_ids, pool_poses = pool_ids[keep], pool_poses[keep]
                else:
                    assert o.pose is not None
                    pose = o.pose.to_matrix()
                view = ViewRecord(id=next_view, pose=pose, candidate_id=candidate,
                                  created_at=time.time())
                next_view += 1
                new_poses.append(pose)
                pos = len(views)
                views.append(view)
            files: dict[str, Any] = {}
            if fr.image_bytes is not None:
                name = f"v{view.id:08d}.rgb.{fr.image_ext}"
                blobs[name] = fr.image_bytes
                files.update(image_file=name, image_encoding=o.image.encoding if o.image else None)
            if fr.depth is not None:
                name = f"v{view.id:08d}.depth.npy"
                buf = io.BytesIO()
                np.save(buf, fr.depth, allow_pickle=False)
                blobs[name] = buf.getvalue()
                files.update(depth_file=name, depth_scale=1.0)
            if files:
                files["intrinsics"] = fr.intrinsics
                view = replace(view, **files)
                views[pos] = view
            touched.append(view)
        h = self._accumulate_views(rec.h_acc, rec.gmap, new_poses, rec)
        new = self._bump(rec, views=tuple(views), next_view_id=next_view, h_acc=h,
                         pool_ids=pool_ids, pool_poses=pool_poses)
        return new, blobs, touched

    def on_observation(self, views: list[ViewRecord]) -> None:
        """Hook: where the mapper integrates new frames.

        Called with the session lock held, after ``views`` (new or given a frame) are
        persisted and Ĥ updated. The mapper attaches itself as ``self.mapper`` and is handed
        the session and the views; it must return quickly (queue the work) and push the
        trained map back through :meth:`replace_map` (under ``self.lock``). Images and depth
        are read with :meth:`view_image` / :meth:`view_depth`.
        """
        if self.mapper is not None:
            self.mapper.integrate(self, views)

    # ------------------------------------------------------------------ select
    def select(self, req: m.SelectRequest) -> m.SelectResponse:
        """Choose the next view; with ``req.pool`` and / or ``req.commit``, the new pool and
        the acquired view are persisted together, after the selection succeeded."""
        with self.lock:
            self._check_open()
            t_core = time.perf_counter()
            rec = self.record
            dirty: list[str] = []
            if req.pool is not None:
                rec = self._pool_changed(rec, req.pool, "body.pool", replace_pool=True)
                dirty.append("pool")
            d = rec.defaults
            method = req.method or d["method"]
            size = req.shortlist_size or d["shortlist_size"]
            embodied_k = req.embodied_k if req.embodied_k is not None else d["embodied_k"]
            fields = req.fields if req.fields is not None else d["fields"]
            if size > self.settings.max_shortlist:
                raise invalid("body.shortlist_size",
                              f"must be <= {self.settings.max_shortlist} (max_shortlist)")
            if len(rec.pool_ids) == 0:
                raise conflict("pool", "the candidate pool is empty: set it first", "empty_pool")
            if len(rec.gmap) == 0:
                raise conflict("gaussians", "the session has no Gaussians yet", "map_empty")
            options = {
                **d.get("config", {}),
                **(req.config or {}),
                "shortlist_size": size,
                "shortlist": req.shortlist or d["shortlist"],
                "embodied_k": embodied_k,
                "seed": req.seed if req.seed is not None else d["seed"],
                "fields": tuple(fields) if fields else None,
            }
            try:
                config = self.backend.make_config(options)
            except ValueError as exc:
                raise invalid(_config_field(str(exc)), str(exc)) from None
            dt = rec.gmap.dtype
            current = None
            current_pose = None
            if req.current_id is not None:
                current = self._pool_index(rec, req.current_id, "body.current_id")
            elif req.current_pose is not None:
                current_pose = torch.from_numpy(req.current_pose.to_matrix()).to(dt)
            elif embodied_k is not None:
                if not rec.views:
                    raise invalid("body.embodied_k", "embodied mode needs the current view: "
                                  "give current_id or current_pose, or acquire a view first")
                current_pose = torch.from_numpy(rec.views[-1].pose).to(dt)
            acquired = (torch.from_numpy(np.stack([v.pose for v in rec.views])).to(dt)
                        if rec.views else None)
            try:
                sel = self.backend.select(
                    method, rec.gmap, rec.h_acc, torch.from_numpy(rec.pool_poses).to(dt),
                    self._intrinsics(rec), config=config, acquired=acquired, current=current,
                    current_pose=current_pose, state=rec.warm_state,
                )
            except ValueError as exc:
                raise invalid(_select_field(str(exc)), str(exc)) from None
            ids = rec.pool_ids
            chosen = int(sel.index)
            chosen_id = int(ids[chosen])
            chosen_pose = rec.pool_poses[chosen]
            committed = None
            if req.commit:
                self._check_view_room(rec, 1, "body.commit")
                view = ViewRecord(id=rec.next_view_id, pose=chosen_pose, candidate_id=chosen_id,
                                  created_at=time.time())
                h = self.backend.accumulate(rec.h_acc,
                                            self._view_info(rec.gmap, chosen_pose, rec))
                rec = self._bump(rec, views=rec.views + (view,), next_view_id=view.id + 1,
                                 h_acc=h, warm_state=_storable_state(sel.state),
                                 **self._without(rec, chosen))
                dirty += ["information", "pool", "warm"]
                committed = _view_out(view)
            if dirty:
                rec = self._commit(rec, dirty)
            scores = sel.scores
            return m.SelectResponse.model_construct(
                session=rec.id,
                method=sel.method,
                chosen=m.Candidate.model_construct(id=chosen_id, pose=pose_out(chosen_pose)),
                shortlist=[
                    m.ScoredCandidate.model_construct(
                        id=int(ids[i]), score=_finite_float(scores[i]) if i in scores else None)
                    for i in sel.shortlist
                ],
                anchor=pose_out(sel.anchor_c2w) if sel.anchor_c2w is not None else None,
                scores=[m.ScoredCandidate.model_construct(id=int(ids[i]), score=_finite_float(v))
                        for i, v in scores.items()],
                eligible=ids[np.asarray(sel.eligible, dtype=np.int64)].tolist(),
                psi_trace=[float(x) for x in sel.psi_trace if math.isfinite(x)],
                latency_ms={k: float(v) for k, v in sel.latency_ms.items()},
                core_ms=(time.perf_counter() - t_core) * 1e3,
                server_ms=None,
                committed=committed,
                version=rec.version,
                time=time.time(),
            )


def _mapper_field(message: str) -> str:
    """The request field a mapper-config error message names."""
    found = re.search(r"(?:mapper\.config\.|MapperConfig\.)(\w+)", message)
    return f"body.mapper.config.{found.group(1)}" if found else "body.mapper.config"


def _storable_state(state: Mapping[str, Any] | None) -> dict[str, Any] | None:
    """The parts of a warm-start state that torch.load(weights_only=True) reads back."""
    if not state:
        return None

    def ok(v: Any) -> Any:
        if isinstance(v, Tensor):
            return v.detach().cpu().clone()
        if isinstance(v, np.ndarray):
            return torch.from_numpy(v.copy())
        if isinstance(v, bool | int | float | str) or v is None:
            return v
        if isinstance(v, list | tuple):
            items = [ok(x) for x in v]
            return None if any(x is _DROP for x in items) else items
        if isinstance(v, dict):
            out = {k: ok(x) for k, x in v.items() if isinstance(k, str | int)}
            return {k: x for k, x in out.items() if x is not _DROP}
        return _DROP

    out = {k: ok(v) for k, v in state.items()}
    return {k: v for k, v in out.items() if v is not _DROP} or None


_DROP = object()


_TOP_LEVEL = ("shortlist_size", "shortlist", "embodied_k", "seed", "fields")


def _config_field(message: str) -> str:
    """The request field a SelectConfig error message names."""
    text = message
    if text.startswith("config."):
        text = text[len("config."):]
    elif text.startswith("config"):
        return "body.config"
    found = re.match(r"((?:anchor|scoring)\.\w+|\w+)", text)
    name = found.group(1) if found else ""
    if name in _TOP_LEVEL:
        return f"body.{name}"
    return f"body.config.{name}" if name else "body.config"


_SELECT_FIELDS = (
    ("candidates", "pool"),
    ("current_pose", "body.current_pose"),
    ("current", "body.current_id"),
    ("method", "body.method"),
    ("config.", "body.config"),
    ("h_acc", "information"),
    ("gmap", "gaussians"),
    ("acquired", "views"),
)


def _select_field(message: str) -> str:
    for prefix, field in _SELECT_FIELDS:
        if message.startswith(prefix):
            return field
    return "body"


def _pool_out(rec: SessionRecord) -> m.PoolOut:
    return m.PoolOut.model_construct(
        candidates=[m.Candidate.model_construct(id=int(i), pose=pose_out(p))
                    for i, p in zip(rec.pool_ids, rec.pool_poses, strict=True)],
        version=rec.version,
    )


def _view_out(v: ViewRecord) -> m.View:
    return m.View.model_construct(
        id=v.id,
        pose=pose_out(v.pose),
        candidate_id=v.candidate_id,
        intrinsics=WireIntrinsics(**v.intrinsics) if v.intrinsics else None,
        has_image=v.image_file is not None,
        has_depth=v.depth_file is not None,
        created_at=v.created_at,
    )


# ============================================================================ the service
class ServiceCore:
    """All sessions, the store, the worker threads, and the one dispatch :meth:`call`."""

    def __init__(self, settings: Settings, backend: MathBackend | None = None) -> None:
        self.settings = settings
        self.backend: MathBackend = backend or NbvBackend()
        self.store = SessionStore(settings.state_dir, fsync=settings.fsync)
        self.sessions: dict[str, SessionCore] = {}
        self.lock = threading.Lock()
        self.executor = ThreadPoolExecutor(settings.workers, thread_name_prefix="agilegs")
        self.started = time.time()
        self.zenoh_enabled = False
        self.metrics: Any = None  # a metrics.Metrics, set by the server
        self.decision_listeners: list[Callable[[str, m.SelectResponse], None]] = []
        self.trainer: Any = None  # a trainer.Trainer while the mapper runs (see load)
        self._tmp = Path(settings.state_dir) / "tmp"
        if settings.torch_threads:
            torch.set_num_threads(settings.torch_threads)

    # ------------------------------------------------------------------ lifecycle
    def load(self) -> int:
        """Load every persisted session; returns how many."""
        self._tmp.mkdir(parents=True, exist_ok=True)
        for stale in self._tmp.iterdir():
            stale.unlink(missing_ok=True)
        for rec in self.store.load_all():
            self.sessions[rec.id] = SessionCore(rec, self)
        log.info("loaded %d session(s) from %s", len(self.sessions), self.settings.state_dir)
        if self.settings.mapper:
            self.start_mapper()
        return len(self.sessions)

    def start_mapper(self) -> None:
        """Start the background mapper (:mod:`agilegs.service.trainer`) for every session;
        sessions with steps still owed (e.g. after a restart) resume training."""
        from .trainer import Trainer

        if self.trainer is None:
            self.trainer = Trainer(self)
            for s in list(self.sessions.values()):
                self.trainer.attach(s)
        self.trainer.start()

    def close(self) -> None:
        if self.trainer is not None:
            self.trainer.close()
        self.executor.shutdown(wait=True, cancel_futures=True)

    # ------------------------------------------------------------------ dispatch
    def call(self, op: str, session: str | None, payload: Any, *, t0: float | None = None
             ) -> BaseModel:
        """Run operation ``op`` on ``session`` with the decoded body ``payload``.

        Returns the operation's response model; raises :class:`ServiceError` for anything
        refused (the session is then unchanged). ``t0`` (``time.perf_counter()`` when the
        request arrived) sets a selection's ``server_ms``.
        """
        spec = OPERATIONS.get(op)
        if spec is None:
            raise not_found("op", f"unknown operation {op!r}")
        req: BaseModel | None = None
        if spec.request is not None:
            if payload is None:
                raise invalid("body", "a request body is required")
            try:
                req = spec.request.model_validate(payload)
            except ValidationError as exc:
                raise validation_error(exc) from None
        if spec.scope == "service":
            if op == "health":
                return self.health()
            if op == "list_sessions":
                return self.list_sessions()
            assert isinstance(req, m.SessionCreate)
            return self.create_session(req)
        s = self.session(session)
        if op == "select":
            assert isinstance(req, m.SelectRequest)
            resp = s.select(req)
            if t0 is not None:
                resp.server_ms = (time.perf_counter() - t0) * 1e3
            if self.metrics is not None:
                self.metrics.observe_selection(resp)
            for listener in self.decision_listeners:
                try:
                    listener(s.id, resp)
                except Exception:  # a listener must never fail the selection
                    log.exception("decision listener failed")
            return resp
        if op == "get_session":
            return s.info()
        if op == "delete_session":
            return self.delete_session(s.id)
        if op == "get_pool":
            return s.get_pool()
        if op == "list_views":
            return s.list_views()
        if op == "get_information":
            return s.get_information()
        if op == "get_gaussians":
            return s.get_gaussians()
        handler = {
            "set_gaussians": s.set_gaussians,
            "add_observations": s.add_observations,
            "commit": s.commit,
            "set_pool": s.set_pool,
            "extend_pool": s.extend_pool,
        }[op]
        result: BaseModel = handler(req)  # type: ignore[operator]
        return result

    def session(self, sid: str | None) -> SessionCore:
        if sid is None or not _SESSION_RE.match(sid):
            raise invalid("session", f"session id must match {m.SESSION_ID_PATTERN}")
        s = self.sessions.get(sid)
        if s is None or s.closed:
            raise not_found("session", f"session {sid!r} does not exist")
        return s

    # ------------------------------------------------------------------ service operations
    def health(self) -> m.Health:
        from importlib.metadata import PackageNotFoundError, version

        try:
            ver = version("agilegs")
        except PackageNotFoundError:  # pragma: no cover - running from a source tree
            ver = "0+unknown"
        return m.Health(version=ver, sessions=len(self.sessions), zenoh=self.zenoh_enabled,
                        uptime_s=time.time() - self.started)

    def list_sessions(self) -> m.SessionList:
        return m.SessionList(sessions=[s.summary() for s in list(self.sessions.values())])

    def delete_session(self, sid: str) -> m.Deleted:
        s = self.session(sid)
        with s.lock:
            if s.closed:
                raise not_found("session", f"session {sid!r} does not exist")
            self.store.delete(sid)
            s.closed = True
            with self.lock:
                self.sessions.pop(sid, None)
        return m.Deleted(id=sid)

    def create_session(self, req: m.SessionCreate) -> m.SessionInfo:
        sid = req.id or f"s-{uuid.uuid4().hex[:12]}"
        with self.lock:
            self._check_new_id(sid)
        intr = req.intrinsics.model_dump()
        pixels = req.intrinsics.width * req.intrinsics.height
        if pixels > self.settings.max_image_pixels:
            raise too_large("body.intrinsics", f"{pixels} pixels exceed max_image_pixels "
                                               f"({self.settings.max_image_pixels})")
        if req.gaussians is None and req.init_gaussians > self.settings.max_gaussians:
            raise too_large("body.init_gaussians", f"exceeds max_gaussians "
                                                   f"({self.settings.max_gaussians})")
        frames = [self.parse_frame(f, i, "body.frames", intr) for i, f in enumerate(req.frames)]
        if len(frames) > self.settings.max_views:
            raise too_many("body.frames", f"{len(frames)} frames exceed max_views "
                                          f"({self.settings.max_views})")
        if req.gaussians is not None:
            gmap = self.parse_gaussians(req.gaussians, "body.gaussians")
        elif any(f.depth is not None for f in frames):
            gmap = gaussians_from_depth(frames, req.init_gaussians, req.seed)
        elif req.bounds is not None:
            gmap = random_gaussians(req.bounds, req.init_gaussians, req.seed)
        else:
            raise invalid("body.bounds", "bounds are required when neither Gaussians nor depth "
                                         "are given")
        if len(gmap) > self.settings.max_gaussians:
            raise too_large("body", f"{len(gmap)} Gaussians exceed max_gaussians "
                                    f"({self.settings.max_gaussians})")
        from .trainer import initial_mapper_state, mapper_config

        try:
            mapper_config(req.mapper.config)
        except ValueError as exc:
            raise invalid(_mapper_field(str(exc)), str(exc)) from None
        now = time.time()
        lam = req.information.lambda_
        rec = SessionRecord(
            id=sid, created_at=now, updated_at=now, version=1,
            intrinsics=intr,
            bounds=req.bounds.model_dump() if req.bounds else None,
            defaults=req.defaults.model_dump(),
            information_config=req.information.model_dump(by_alias=True),
            gmap=gmap,
            h_acc=self.backend.init_information(gmap, lam),
            pool_ids=np.zeros(0, dtype=np.int64), pool_poses=np.zeros((0, 4, 4)),
            next_candidate_id=0, views=(), next_view_id=0,
            mapper=initial_mapper_state(req.mapper),
        )
        draft = SessionCore(rec, self)
        if req.pool is not None:
            rec = draft._pool_changed(rec, req.pool, "body.pool", replace_pool=True)
        blobs: dict[str, bytes] = {}
        if frames:
            rec, blobs, _ = draft._integrate(rec, frames, "body.frames")
        rec = replace(rec, version=1, updated_at=now)
        with self.lock:
            self._check_new_id(sid)
            try:
                rec = self.store.create(rec, blobs)
            except FileExistsError:
                raise conflict("body.id", f"session {sid!r} already exists") from None
            s = SessionCore(rec, self)
            if self.trainer is not None:
                self.trainer.attach(s)
            self.sessions[sid] = s
        if frames:
            s.on_observation(list(rec.views))
        return s.info()

    def _check_new_id(self, sid: str) -> None:
        if sid in self.sessions:
            raise conflict("body.id", f"session {sid!r} already exists")
        if len(self.sessions) >= self.settings.max_sessions:
            raise too_many("body", f"max_sessions ({self.settings.max_sessions}) reached")

    # ------------------------------------------------------------------ input parsing
    def parse_gaussians(self, g: m.GaussiansIn, field: str) -> GaussianMap:
        if g.format == "arrays":
            assert g.arrays is not None
            n = g.arrays.means.shape[0] if g.arrays.means.shape else 0
            if n > self.settings.max_gaussians:
                raise too_large(f"{field}.arrays", f"{n} Gaussians exceed max_gaussians "
                                                   f"({self.settings.max_gaussians})")
            return gaussians_from_arrays(g.arrays, f"{field}.arrays")
        assert g.data is not None
        self._tmp.mkdir(parents=True, exist_ok=True)
        path = self._tmp / f"upload-{uuid.uuid4().hex}.{g.format}"
        try:
            path.write_bytes(g.data)
            try:
                gmap = self.backend.load_gaussians(path)
            except (ValueError, OSError, IndexError, KeyError, TypeError) as exc:
                msg = str(exc).replace(str(path), g.format)
                raise invalid(f"{field}.data", f"cannot read the {g.format} file: {msg}") from None
        finally:
            path.unlink(missing_ok=True)
        if len(gmap) > self.settings.max_gaussians:
            raise too_large(f"{field}.data", f"{len(gmap)} Gaussians exceed max_gaussians "
                                             f"({self.settings.max_gaussians})")
        for name, t in gmap.items():
            _check_finite_tensor(t, f"{field}.data ({name})")
        return gmap

    def parse_frame(self, o: m.ObservationIn, index: int, field: str,
                    session_intrinsics: Mapping[str, Any]) -> _Frame:
        where = f"{field}[{index}]"
        intr = o.intrinsics.model_dump() if o.intrinsics is not None else dict(session_intrinsics)
        h, w = int(intr["height"]), int(intr["width"])
        fr = _Frame(index=index, obs=o, intrinsics=intr)
        limit = self.settings.max_image_pixels
        if o.image is not None:
            if h * w > limit:
                raise too_large(f"{where}.image", f"{w}x{h} pixels exceed max_image_pixels "
                                                  f"({limit})")
            fr.image_bytes, fr.image_ext, fr.image_rgb = _parse_image(o.image, h, w, limit,
                                                                      f"{where}.image")
        if o.depth is not None:
            if list(o.depth.shape) != [h, w]:
                raise invalid(f"{where}.depth", f"depth has shape {o.depth.shape}, the "
                                                f"intrinsics say [{h}, {w}]")
            if h * w > limit:
                raise too_large(f"{where}.depth", f"{w}x{h} pixels exceed max_image_pixels")
            d = o.depth.to_numpy().astype(np.float32) * np.float32(o.depth_scale)
            if not np.isfinite(d).all():
                raise invalid(f"{where}.depth", "contains NaN or infinite values")
            if (d < 0).any():
                raise invalid(f"{where}.depth", "contains negative values")
            fr.depth = d
        if o.pose is not None:
            fr.pose = o.pose.to_matrix()
        return fr


def _parse_image(img: m.ImageData, h: int, w: int, limit: int, field: str
                 ) -> tuple[bytes, str, np.ndarray]:
    """Check an image (size, values, decodability); returns (bytes to store, ext, pixels)."""
    if img.encoding == "raw":
        assert img.shape is not None
        if img.shape[:2] != [h, w]:
            raise invalid(f"{field}.shape", f"image is {img.shape[:2]} (H, W), the intrinsics say "
                                            f"[{h}, {w}]")
        a = img.to_numpy()
        if a.dtype.kind == "f":
            if not np.isfinite(a).all():
                raise invalid(f"{field}.data", "contains NaN or infinite values")
            if a.min() < 0 or a.max() > 1:
                raise invalid(f"{field}.data", "float32 pixels must lie in [0, 1]")
        buf = io.BytesIO()
        np.save(buf, np.ascontiguousarray(a), allow_pickle=False)
        return buf.getvalue(), "npy", a
    from PIL import Image, UnidentifiedImageError

    want = "PNG" if img.encoding == "png" else "JPEG"
    try:
        with Image.open(io.BytesIO(img.data)) as im:
            if im.format != want:
                raise invalid(f"{field}.data", f"data is not a {img.encoding} file "
                                               f"({im.format or 'unknown'})")
            if im.size[0] * im.size[1] > limit:
                raise too_large(f"{field}.data", "image exceeds max_image_pixels")
            if im.size != (w, h):
                raise invalid(f"{field}.data", f"image is {im.size[0]}x{im.size[1]}, the "
                                               f"intrinsics say {w}x{h}")
            im.load()
            rgb = np.asarray(im.convert("RGB"))
    except ServiceError:
        raise
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError, Image.DecompressionBombError
            ) as exc:
        raise invalid(f"{field}.data", f"cannot decode the {img.encoding} image: {exc}") from None
    return img.data, "png" if img.encoding == "png" else "jpg", rgb


def gaussians_from_depth(frames: list[_Frame], count: int, seed: int) -> GaussianMap:
    """Back-project the frames' depth (the mapper's :func:`backproject_depth`) and keep
    ``count`` coloured isotropic Gaussians, scaled by their nearest-neighbour distances."""
    from .mapper import backproject_depth, nearest_neighbour_scales

    pts, cols = [], []
    for fr in frames:
        if fr.depth is None or fr.pose is None or fr.intrinsics is None:
            continue
        cam = Camera(c2w=torch.from_numpy(fr.pose), intrinsics=nbv_intrinsics(fr.intrinsics))
        rgb = None
        if fr.image_rgb is not None:
            rgb = torch.from_numpy(np.asarray(fr.image_rgb, dtype=np.float64))
            if fr.image_rgb.dtype == np.uint8:
                rgb = rgb / 255.0
        p, c = backproject_depth(cam, torch.from_numpy(fr.depth).double(), rgb)
        pts.append(p)
        cols.append(c)
    points = torch.cat(pts) if pts else torch.zeros(0, 3)
    if points.shape[0] == 0:
        raise invalid("body.frames", "the depth maps hold no valid (positive) value")
    colors = torch.cat(cols)
    n = min(count, points.shape[0]) if count > 0 else points.shape[0]
    if n < points.shape[0]:
        keep = torch.randperm(points.shape[0], generator=torch.Generator().manual_seed(seed))[:n]
        points, colors = points[keep], colors[keep]
    points = points.float()
    return GaussianMap.from_points(points, colors.float().clamp(0, 1),
                                   scale=nearest_neighbour_scales(points), opacity=0.5)
