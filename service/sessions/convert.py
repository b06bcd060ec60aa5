"""Wire models to tensors and back: intrinsics, poses, Gaussians, images, depth, warm state.

Everything here checks what it converts (shapes, finiteness, sizes against the server's
limits) and raises a :class:`~agilegs.service.errors.ServiceError` naming the field.
"""

from __future__ import annotations

import hashlib
import io
import math
import uuid
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from agilegs import schemas as m
from agilegs.config.geometry import MAX_COORD
from agilegs.config.selection import FIELD_NAMES
from agilegs.schemas import Intrinsics as WireIntrinsics
from agilegs.schemas import Pose
from agilegs.schemas.geometry import PoseArrayList

from ..errors import ServiceError, conflict, invalid, too_large
from ..mapper.points import backproject_depth, nearest_neighbour_scales
from ..nbv import Camera, GaussianMap, Intrinsics
from ..store.records import SessionRecord, ViewRecord

__all__ = [
    "Frame",
    "empty_map",
    "finite_float",
    "gaussians_from_arrays",
    "gaussians_from_depth",
    "gaussians_file",
    "information_summary",
    "nbv_intrinsics",
    "parse_frame",
    "parse_gaussians",
    "parse_image",
    "pool_out",
    "pose_out",
    "poses_array",
    "random_gaussians",
    "storable_state",
    "view_out",
]


def nbv_intrinsics(d: Mapping[str, Any]) -> Intrinsics:
    return Intrinsics(
        fx=float(d["fx"]), fy=float(d["fy"]), cx=float(d["cx"]), cy=float(d["cy"]),
        width=int(d["width"]), height=int(d["height"]),
    )


def pose_out(matrix: np.ndarray | Tensor) -> Pose:
    """A pose [4, 4] for a reply. Its translation is clipped to the wire's bound
    (:data:`~agilegs.config.geometry.MAX_COORD`): a pose computed in float32 near the bound
    (an anchor started from a candidate there) may round past it."""
    a = matrix.detach().cpu().numpy() if isinstance(matrix, Tensor) else np.asarray(matrix)
    a = a.astype(np.float64)
    a[:3, 3] = np.clip(a[:3, 3], -MAX_COORD, MAX_COORD)
    return Pose.from_matrix(a, validate=False)


def poses_array(poses: list[Pose]) -> np.ndarray:
    """Camera-to-world matrices [D, 4, 4] (float64) of validated wire poses."""
    if not poses:
        return np.zeros((0, 4, 4))
    if isinstance(poses, PoseArrayList):  # validated as one array: it is there already
        return poses.matrices
    if all(p.matrix is not None for p in poses):  # the common case, in one conversion
        return np.asarray([p.matrix for p in poses], dtype=np.float64)
    return np.stack([p.to_matrix() for p in poses])


def finite_float(x: float) -> float | None:
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
            sum=finite_float(float(t.sum(dtype=torch.float64))),
            min=finite_float(float(t.min())) if t.numel() else None,
            max=finite_float(float(t.max())) if t.numel() else None,
        )
    return m.InformationSummary(fields=fields, digest=digest.hexdigest())


def check_finite_tensor(t: Tensor, field: str) -> None:
    if not bool(torch.isfinite(t).all()):
        raise invalid(field, "contains NaN or infinite values")


def gaussians_from_arrays(a: m.GaussianArrays, field: str) -> GaussianMap:
    tensors: dict[str, Tensor] = {}
    for name in FIELD_NAMES:
        arr: m.NDArray = getattr(a, name)
        if arr.dtype not in ("float32", "float64"):
            raise invalid(f"{field}.{name}.dtype", "must be float32 or float64")
        t = torch.from_numpy(arr.to_numpy().astype(np.float32))
        check_finite_tensor(t, f"{field}.{name}")
        tensors[name] = t
    try:
        return GaussianMap(**tensors)
    except ValueError as exc:
        raise invalid(field, str(exc)) from None


def gaussians_file(out: m.GaussiansOut, fmt: str) -> bytes:
    """The Gaussians of a ``get_gaussians`` answer as the file :meth:`GaussianMap.save`
    writes: the Inria 3DGS ``.ply`` (``fmt="ply"``: the float32 parameters as they are) or
    the antimatter15 ``.splat``; 409 while the map has no Gaussians."""
    if out.count == 0:
        raise conflict("gaussians", "the session's map has no Gaussians yet: there is no "
                                    f".{fmt} file to give")
    arrays = {k: torch.from_numpy(np.array(v, dtype=np.float32)) for k, v in out.to_numpy().items()}
    return GaussianMap(**arrays).to_bytes(fmt)


def random_gaussians(bounds: m.Bounds, count: int, seed: int) -> GaussianMap:
    """``count`` grey, faint, isotropic Gaussians uniformly inside ``bounds`` (a prior)."""
    lo = torch.tensor(bounds.min, dtype=torch.float64)
    hi = torch.tensor(bounds.max, dtype=torch.float64)
    if count == 0:
        return empty_map()
    g = torch.Generator().manual_seed(seed)
    pts = lo + (hi - lo) * torch.rand(count, 3, generator=g, dtype=torch.float64)
    volume = float(torch.prod(hi - lo))
    scale = 0.5 * (volume / count) ** (1 / 3)
    colors = torch.full((count, 3), 0.5, dtype=torch.float64)
    return GaussianMap.from_points(pts.float(), colors.float(), scale=scale, opacity=0.1)


def empty_map() -> GaussianMap:
    z = torch.zeros
    return GaussianMap(means=z(0, 3), log_scales=z(0, 3), quats=z(0, 4), opacity_logits=z(0),
                       sh=z(0, 1, 3))


@dataclass
class Frame:
    """A validated observation, ready to become (or attach to) a view."""

    index: int
    obs: m.ObservationIn
    intrinsics: dict[str, Any] | None
    image_bytes: bytes | None = None
    image_ext: str | None = None
    image_rgb: np.ndarray | None = None  # decoded, for depth initialisation
    depth: np.ndarray | None = None  # [H, W] float32, scene units (0: missing)
    pose: np.ndarray | None = None


def parse_gaussians(g: m.GaussiansIn, field: str, *, max_gaussians: int, tmp_dir: Path
                    ) -> GaussianMap:
    """The Gaussians of an upload (arrays, or a .ply / .splat file read through ``tmp_dir``)."""
    if g.format == "arrays":
        assert g.arrays is not None
        n = g.arrays.means.shape[0] if g.arrays.means.shape else 0
        if n > max_gaussians:
            raise too_large(f"{field}.arrays", f"{n} Gaussians exceed max_gaussians "
                                               f"({max_gaussians})")
        return gaussians_from_arrays(g.arrays, f"{field}.arrays")
    assert g.data is not None
    tmp_dir.mkdir(parents=True, exist_ok=True)
    path = tmp_dir / f"upload-{uuid.uuid4().hex}.{g.format}"
    try:
        path.write_bytes(g.data)
        try:
            gmap = GaussianMap.load(path)
        except (ValueError, OSError, IndexError, KeyError, TypeError) as exc:
            msg = str(exc).replace(str(path), g.format)
            raise invalid(f"{field}.data", f"cannot read the {g.format} file: {msg}") from None
    finally:
        path.unlink(missing_ok=True)
    if len(gmap) > max_gaussians:
        raise too_large(f"{field}.data", f"{len(gmap)} Gaussians exceed max_gaussians "
                                         f"({max_gaussians})")
    for name, t in gmap.items():
        check_finite_tensor(t, f"{field}.data ({name})")
    return gmap


def parse_frame(o: m.ObservationIn, index: int, field: str,
                session_intrinsics: Mapping[str, Any], *, max_image_pixels: int) -> Frame:
    """A validated observation (image decoded, depth checked), ready to become a view."""
    where = f"{field}[{index}]"
    intr = o.intrinsics.model_dump() if o.intrinsics is not None else dict(session_intrinsics)
    h, w = int(intr["height"]), int(intr["width"])
    fr = Frame(index=index, obs=o, intrinsics=intr)
    limit = max_image_pixels
    if o.intrinsics is not None and h * w > limit:
        raise too_large(f"{where}.intrinsics", f"{w}x{h} pixels exceed max_image_pixels "
                                               f"({limit})")
    if o.image is not None:
        if h * w > limit:
            raise too_large(f"{where}.image", f"{w}x{h} pixels exceed max_image_pixels "
                                              f"({limit})")
        fr.image_bytes, fr.image_ext, fr.image_rgb = parse_image(o.image, h, w, limit,
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


def parse_image(img: m.ImageData, h: int, w: int, limit: int, field: str
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


def gaussians_from_depth(frames: list[Frame], count: int, seed: int) -> GaussianMap:
    """Back-project the frames' depth (the mapper's :func:`backproject_depth`) and keep
    ``count`` coloured isotropic Gaussians, scaled by their nearest-neighbour distances."""
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


def pool_out(rec: SessionRecord) -> m.PoolOut:
    return m.PoolOut.model_construct(
        candidates=[m.Candidate.model_construct(id=int(i), pose=pose_out(p))
                    for i, p in zip(rec.pool_ids, rec.pool_poses, strict=True)],
        version=rec.version,
    )


def view_out(v: ViewRecord) -> m.View:
    return m.View.model_construct(
        id=v.id,
        pose=pose_out(v.pose),
        candidate_id=v.candidate_id,
        intrinsics=WireIntrinsics(**v.intrinsics) if v.intrinsics else None,
        has_image=v.image_file is not None,
        has_depth=v.depth_file is not None,
        created_at=v.created_at,
    )


def storable_state(state: Mapping[str, Any] | None) -> dict[str, Any] | None:
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
