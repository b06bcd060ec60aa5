"""Gaussian maps: the parameter tensors of a 3D Gaussian Splatting scene.

Conventions (docs/conventions.md): means [N,3] in world units, ``log_scales`` [N,3] (natural log of
the per-axis standard deviations), ``quats`` [N,4] in (w, x, y, z) order (``render``
normalises them), ``opacity_logits`` [N] (opacity = sigmoid), ``sh`` [N,(d+1)^2,3] spherical
harmonic coefficients, DC first; colour = 0.5 + C0 * sh_DC + higher bands, clamped at 0, as in
the reference 3DGS implementation.

File IO (``GaussianMap.load`` / ``GaussianMap.save`` / ``load_scene``), format by suffix:

* ``.ply``: the Inria 3DGS layout (one ``vertex`` element, float32 properties
  ``x y z nx ny nz f_dc_0..2 f_rest_0..M-1 opacity scale_0..2 rot_0..3``, ``M = 3((d+1)^2-1)``;
  ``f_rest`` is channel-major: the [N, K-1, 3] tensor transposed to [N, 3, K-1] and flattened,
  as the reference code writes it). Stored values are the raw parameters (log scales, opacity
  logits, unnormalised quaternions), so a float32 map round-trips bit-exactly. Loading accepts
  float64 / integer properties (cast to float32), extra properties (ignored), any byte order
  and ASCII PLY.
* ``.splat``: the antimatter15 packing, header-less 32-byte records: position 3 x f32, linear
  scale 3 x f32, RGBA uint8 (A = opacity), quaternion (w, x, y, z) uint8 as ``q*128+128``.
  Saving is lossy: spherical harmonics beyond DC are dropped, colour and opacity are
  quantised to 1/255, the quaternion to 1/128 (and normalised), colour is clamped to [0, 1].
  Loading inverts the packing (``dc = (rgb/255 - 0.5)/C0``, ``opacity_logit =
  logit(clip(a/255, 1e-4, 1-1e-4))``, ``log_scale = log(scale)``, ``quat = (q-128)/128``
  normalised). ``load(save(m))`` is a fixed point: saving and loading it again changes
  nothing (the quaternion bytes are chosen so that this holds).

Loaded maps are float32 on the CPU. Bad files raise ``ValueError`` naming the problem.
"""

from __future__ import annotations

import io
import math
import os
import re
from collections.abc import Iterator
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from agilegs.config.selection import FIELD_NAMES as FIELD_NAMES  # the parameter blocks

SH_C0 = 0.28209479177387814

PathLike = str | os.PathLike[str]

#: Suffix (lower case) -> format name understood by ``GaussianMap.load`` / ``save``.
SUFFIXES: dict[str, str] = {".ply": "ply", ".splat": "splat"}

#: One ``.splat`` record (32 bytes, little endian).
SPLAT_DTYPE = np.dtype(
    [("position", "<f4", (3,)), ("scale", "<f4", (3,)), ("rgba", "u1", (4,)), ("rot", "u1", (4,))]
)
#: Opacities read from ``.splat`` are clipped to [eps, 1 - eps] before the logit.
SPLAT_OPACITY_EPS = 1e-4
#: ``.splat`` scales of exactly 0 (degenerate, flat Gaussians) are read as this value.
SPLAT_MIN_SCALE = 1e-10

PLY_REQUIRED: tuple[str, ...] = (
    "x", "y", "z",
    "f_dc_0", "f_dc_1", "f_dc_2",
    "opacity",
    "scale_0", "scale_1", "scale_2",
    "rot_0", "rot_1", "rot_2", "rot_3",
)  # fmt: skip


@dataclass
class GaussianMap:
    """A set of N anisotropic 3D Gaussians.

    Args:
        means: centres [N, 3].
        log_scales: log of the per-axis standard deviations [N, 3].
        quats: rotations as quaternions (w, x, y, z) [N, 4], not necessarily unit.
        opacity_logits: opacity before the sigmoid [N].
        sh: spherical-harmonic colour coefficients [N, (d+1)^2, 3], DC first.
    """

    means: Tensor
    log_scales: Tensor
    quats: Tensor
    opacity_logits: Tensor
    sh: Tensor

    def __post_init__(self) -> None:
        n = self.means.shape[0] if self.means.ndim == 2 else -1
        expect = {
            "means": (n, 3),
            "log_scales": (n, 3),
            "quats": (n, 4),
            "opacity_logits": (n,),
        }
        if self.means.ndim != 2 or self.means.shape[1] != 3:
            raise ValueError(f"means must have shape [N, 3], got {tuple(self.means.shape)}")
        for name, shape in expect.items():
            t = getattr(self, name)
            if tuple(t.shape) != shape:
                raise ValueError(f"{name} must have shape {list(shape)}, got {list(t.shape)}")
        if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            raise ValueError(f"sh must have shape [N, (d+1)^2, 3], got {list(self.sh.shape)}")
        k = self.sh.shape[1]
        d = int(round(math.sqrt(k))) - 1
        if (d + 1) ** 2 != k or d > 3 or d < 0:
            raise ValueError(f"sh must hold (d+1)^2 coefficients with d <= 3, got {k}")

    # ------------------------------------------------------------------ basic properties
    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def num_gaussians(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return int(round(math.sqrt(self.sh.shape[1]))) - 1

    @property
    def device(self) -> torch.device:
        return self.means.device

    @property
    def dtype(self) -> torch.dtype:
        return self.means.dtype

    def tensors(self) -> dict[str, Tensor]:
        """The five parameter tensors keyed by field name, in field order."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def items(self) -> Iterator[tuple[str, Tensor]]:
        return iter(self.tensors().items())

    def to(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> GaussianMap:
        return GaussianMap(**{k: v.to(device=device, dtype=dtype) for k, v in self.items()})

    def detach(self) -> GaussianMap:
        return GaussianMap(**{k: v.detach() for k, v in self.items()})

    def clone(self) -> GaussianMap:
        return GaussianMap(**{k: v.detach().clone() for k, v in self.items()})

    def requires_grad_(self, flag: bool = True) -> GaussianMap:
        for v in self.tensors().values():
            v.requires_grad_(flag)
        return self

    def subset(self, index: Tensor) -> GaussianMap:
        """The Gaussians selected by ``index`` (bool mask [N] or integer indices [M])."""
        return GaussianMap(**{k: v[index] for k, v in self.items()})

    # ------------------------------------------------------------------ derived quantities
    @property
    def scales(self) -> Tensor:
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> Tensor:
        return torch.sigmoid(self.opacity_logits)

    @staticmethod
    def sh_dc_from_rgb(rgb: Tensor) -> Tensor:
        """DC coefficients [N, 3] that give colour ``rgb`` [N, 3] (inverse of 0.5 + C0 * dc)."""
        return (rgb - 0.5) / SH_C0

    # ------------------------------------------------------------------ file IO
    @classmethod
    def load(cls, path: PathLike) -> GaussianMap:
        """Read a ``.ply`` (Inria 3DGS) or ``.splat`` (antimatter15) file; float32, CPU.

        Raises:
            FileNotFoundError: no such file.
            ValueError: unknown suffix, empty / truncated / malformed file, missing PLY
                properties, NaN or infinite values; the message says which.
        """
        p = Path(path)
        fmt = _format_of(p)
        if not p.is_file():
            raise FileNotFoundError(f"{p}: no such Gaussian map file")
        if p.stat().st_size == 0:
            raise ValueError(f"{p}: file is empty (0 bytes)")
        return _load_ply(p) if fmt == "ply" else _load_splat(p)

    def save(self, path: PathLike) -> None:
        """Write the map as ``.ply`` (exact, float32) or ``.splat`` (quantised; see module doc).

        Tensors are detached, moved to the CPU and cast to float32. The file is written to a
        temporary name and renamed, so readers never see half a file.

        Raises:
            ValueError: unknown suffix, an empty map, or NaN / infinite parameters.
        """
        p = Path(path)
        data = self.to_bytes(_format_of(p), what=str(p))
        tmp = p.with_name(f".{p.name}.tmp{os.getpid()}")
        try:
            tmp.write_bytes(data)
            os.replace(tmp, p)
        finally:
            if tmp.exists():
                tmp.unlink()

    def to_bytes(self, fmt: str, *, what: str = "the map") -> bytes:
        """The bytes :meth:`save` writes for format ``fmt`` (``"ply"`` or ``"splat"``).

        Raises:
            ValueError: an unknown format, an empty map, or NaN / infinite parameters
                (``what`` names the map in the message).
        """
        if fmt not in ("ply", "splat"):
            raise ValueError(f"unknown Gaussian map format {fmt!r}; supported: ply, splat")
        if self.num_gaussians == 0:
            raise ValueError(f"{what}: refusing to save an empty map (0 Gaussians)")
        for name, t in self.items():
            bad = int((~torch.isfinite(t.detach())).sum())
            if bad:
                raise ValueError(f"cannot save {what}: {name} has {bad} NaN or infinite values")
        return _ply_bytes(self) if fmt == "ply" else _splat_bytes(self)

    @classmethod
    def from_points(
        cls,
        points: Tensor,
        colors: Tensor,
        *,
        scale: float | Tensor = 0.01,
        opacity: float = 0.5,
        sh_degree: int = 0,
    ) -> GaussianMap:
        """Isotropic Gaussians at ``points`` [N,3] with colours ``colors`` [N,3] in [0,1]."""
        n = points.shape[0]
        dt, dev = points.dtype, points.device
        if isinstance(scale, Tensor):
            s = scale.to(dt).reshape(-1, 1).expand(n, 3)
        else:
            s = torch.full((n, 3), float(scale), dtype=dt, device=dev)
        quats = torch.zeros(n, 4, dtype=dt, device=dev)
        quats[:, 0] = 1.0
        sh = torch.zeros(n, (sh_degree + 1) ** 2, 3, dtype=dt, device=dev)
        sh[:, 0] = cls.sh_dc_from_rgb(colors.to(dt))
        logit = math.log(opacity / (1.0 - opacity))
        return cls(
            means=points.clone(),
            log_scales=torch.log(s).clone(),
            quats=quats,
            opacity_logits=torch.full((n,), logit, dtype=dt, device=dev),
            sh=sh,
        )


# ---------------------------------------------------------------------------------- file IO
def _format_of(path: Path) -> str:
    fmt = SUFFIXES.get(path.suffix.lower())
    if fmt is None:
        known = ", ".join(SUFFIXES)
        raise ValueError(
            f"{path}: unknown file suffix {path.suffix!r}; supported Gaussian map formats: {known}"
        )
    return fmt


def _cpu_f64(t: Tensor) -> Tensor:
    return t.detach().to(device="cpu", dtype=torch.float64)


def _check_finite(path: Path, what: str, a: np.ndarray) -> None:
    bad = int((~np.isfinite(a)).sum())
    if bad:
        raise ValueError(f"{path}: {what} has {bad} NaN or infinite values")


# --- .splat ----------------------------------------------------------------------------
def _quat_bytes(q: np.ndarray) -> np.ndarray:
    """Quaternions [N, 4] -> uint8 ``q/|q| * 128 + 128`` (zero quaternions -> identity)."""
    q = q.astype(np.float64)
    n = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(n > 0, q / np.where(n > 0, n, 1.0), np.array([1.0, 0.0, 0.0, 0.0]))
    return np.clip(np.rint(q * 128.0 + 128.0), 0, 255).astype(np.uint8)


def _quat_from_bytes(b: np.ndarray) -> np.ndarray:
    """uint8 [N, 4] -> unit float32 quaternions ``(b - 128)/128`` normalised (all-128 -> id)."""
    q = (b.astype(np.float64) - 128.0) / 128.0
    n = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(n > 0, q / np.where(n > 0, n, 1.0), np.array([1.0, 0.0, 0.0, 0.0]))
    return q.astype(np.float32)


def _fixed_point_quat_bytes(q: np.ndarray, max_iter: int = 8) -> np.ndarray:
    """Quantise like ``_quat_bytes`` but return bytes that decode and re-encode to themselves.

    Normalising the decoded quaternion can move a component across a rounding boundary, so
    plain quantisation is not idempotent under load/save. Re-encoding the decoded value
    reaches a fixed point within one or two steps (at most one quantisation step away).
    """
    b = _quat_bytes(q)
    for _ in range(max_iter):
        b2 = _quat_bytes(_quat_from_bytes(b))
        changed = (b2 != b).any(axis=1)
        if not changed.any():
            break
        b = b2
    return b


def _splat_bytes(m: GaussianMap) -> bytes:
    n = m.num_gaussians
    rec = np.zeros(n, dtype=SPLAT_DTYPE)
    rec["position"] = _cpu_f64(m.means).to(torch.float32).numpy()
    scale = torch.exp(_cpu_f64(m.log_scales)).to(torch.float32)
    if not torch.isfinite(scale).all():
        raise ValueError("cannot save .splat: exp(log_scales) overflows float32")
    rec["scale"] = scale.numpy()
    rgb = (0.5 + SH_C0 * _cpu_f64(m.sh[:, 0, :])).clamp(0.0, 1.0)
    alpha = torch.sigmoid(_cpu_f64(m.opacity_logits))[:, None]
    rec["rgba"] = torch.round(torch.cat([rgb, alpha], dim=1) * 255.0).to(torch.uint8).numpy()
    rec["rot"] = _fixed_point_quat_bytes(_cpu_f64(m.quats).numpy())
    return rec.tobytes()


def _load_splat(path: Path) -> GaussianMap:
    raw = path.read_bytes()
    size = len(raw)
    rs = SPLAT_DTYPE.itemsize
    if size % rs:
        raise ValueError(
            f"{path}: size {size} bytes is not a multiple of the {rs}-byte .splat record "
            f"({size // rs} whole records + {size % rs} stray bytes): truncated or not a "
            ".splat file"
        )
    rec = np.frombuffer(raw, dtype=SPLAT_DTYPE)
    pos = np.array(rec["position"], dtype=np.float32)
    scale = np.array(rec["scale"], dtype=np.float64)
    _check_finite(path, "position", pos)
    _check_finite(path, "scale", scale)
    neg = int((scale < 0).sum())
    if neg:
        raise ValueError(f"{path}: scale has {neg} negative values")
    scale = np.maximum(scale, SPLAT_MIN_SCALE)
    rgba = rec["rgba"].astype(np.float64) / 255.0
    dc = (rgba[:, :3] - 0.5) / SH_C0
    a = np.clip(rgba[:, 3], SPLAT_OPACITY_EPS, 1.0 - SPLAT_OPACITY_EPS)
    logit = np.log(a) - np.log1p(-a)
    return GaussianMap(
        means=torch.from_numpy(pos),
        log_scales=torch.from_numpy(np.log(scale).astype(np.float32)),
        quats=torch.from_numpy(_quat_from_bytes(rec["rot"])),
        opacity_logits=torch.from_numpy(logit.astype(np.float32)),
        sh=torch.from_numpy(dc.astype(np.float32)[:, None, :].copy()),
    )


# --- .ply ------------------------------------------------------------------------------
_F_REST = re.compile(r"^f_rest_(\d+)$")


def _ply_property_names(sh_rest: int) -> list[str]:
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(sh_rest)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def _ply_bytes(m: GaussianMap) -> bytes:
    from plyfile import PlyData, PlyElement

    n = m.num_gaussians

    def f32(t: Tensor) -> np.ndarray:
        return t.detach().to(device="cpu", dtype=torch.float32).numpy()

    sh = m.sh.detach()
    k = sh.shape[1]
    rest = f32(sh[:, 1:, :].transpose(1, 2).reshape(n, 3 * (k - 1)))
    cols = np.concatenate(
        [
            f32(m.means),
            np.zeros((n, 3), dtype=np.float32),
            f32(sh[:, 0, :]),
            rest,
            f32(m.opacity_logits)[:, None],
            f32(m.log_scales),
            f32(m.quats),
        ],
        axis=1,
    )
    if not np.isfinite(cols).all():
        raise ValueError("cannot save .ply: parameter values overflow float32")
    names = _ply_property_names(3 * (k - 1))
    arr = np.empty(n, dtype=[(name, "<f4") for name in names])
    for i, name in enumerate(names):
        arr[name] = cols[:, i]
    buf = io.BytesIO()
    PlyData([PlyElement.describe(arr, "vertex")], text=False, byte_order="<").write(buf)
    return buf.getvalue()


def _load_ply(path: Path) -> GaussianMap:
    from plyfile import PlyData

    try:
        # parse from memory: no memory map left open, no file handle leaked by the ASCII path
        ply = PlyData.read(io.BytesIO(path.read_bytes()))
    except Exception as exc:  # plyfile raises several types; report them all as ValueError
        msg = str(exc)
        if "end-of-file" in msg or "end of file" in msg:
            raise ValueError(f"{path}: truncated PLY file ({msg})") from exc
        raise ValueError(f"{path}: malformed PLY file ({type(exc).__name__}: {msg})") from exc
    names = [e.name for e in ply.elements]
    if "vertex" not in names:
        raise ValueError(f"{path}: PLY has no 'vertex' element (elements: {names})")
    data = ply["vertex"].data
    n = int(len(data))
    props = list(data.dtype.names or ())
    missing = [p for p in PLY_REQUIRED if p not in props]
    if missing:
        raise ValueError(
            f"{path}: PLY vertex element is missing required properties {missing} (has {props})"
        )
    rest_idx = sorted(int(mt.group(1)) for p in props if (mt := _F_REST.match(p)))
    n_rest = len(rest_idx)
    if rest_idx != list(range(n_rest)):
        raise ValueError(f"{path}: PLY f_rest_* properties are not numbered 0..{n_rest - 1}")
    k = n_rest // 3 + 1
    if n_rest % 3 or k not in (1, 4, 9, 16):
        raise ValueError(
            f"{path}: PLY has {n_rest} f_rest_* properties; expected 0, 9, 24 or 45 "
            "(spherical harmonics of degree 0..3)"
        )
    if n == 0:
        raise ValueError(f"{path}: PLY vertex element has no Gaussians (0 vertices)")

    def col(name: str) -> np.ndarray:
        v: Any = data[name]
        if v.dtype == object or not np.issubdtype(v.dtype, np.number):
            raise ValueError(f"{path}: PLY property {name!r} must be a numeric scalar")
        with np.errstate(over="ignore", invalid="ignore"):  # out-of-range -> inf, reported
            out = np.array(v, dtype=np.float32)  # a contiguous copy (not a view of the file)
        _check_finite(path, f"PLY property {name!r}", out)
        return out

    def block(names: list[str]) -> np.ndarray:
        if not names:
            return np.zeros((n, 0), dtype=np.float32)
        return np.stack([col(nm) for nm in names], axis=1)

    means = block(["x", "y", "z"])
    dc = block(["f_dc_0", "f_dc_1", "f_dc_2"])
    rest = block([f"f_rest_{i}" for i in range(n_rest)])
    opacity = col("opacity")
    log_scales = block(["scale_0", "scale_1", "scale_2"])
    quats = block(["rot_0", "rot_1", "rot_2", "rot_3"])
    rest = rest.reshape(n, 3, k - 1).transpose(0, 2, 1)  # channel-major -> [N, K-1, 3]
    sh = np.ascontiguousarray(np.concatenate([dc[:, None, :], rest], axis=1))
    return GaussianMap(
        means=torch.from_numpy(means),
        log_scales=torch.from_numpy(log_scales),
        quats=torch.from_numpy(quats),
        opacity_logits=torch.from_numpy(opacity),
        sh=torch.from_numpy(sh),
    )


# --- scenes ----------------------------------------------------------------------------
def load_scene(path: PathLike, max_gaussians: int | None = None, seed: int = 0) -> GaussianMap:
    """Load a scene file (or a folder holding exactly one ``.ply`` / ``.splat`` file).

    With ``max_gaussians`` set and the scene larger, keeps a seeded uniform random subset of
    ``max_gaussians`` Gaussians (in file order; the same ``seed`` gives the same subset).
    The kept Gaussians are unchanged, so a heavily subsampled scene renders sparser.
    """
    p = Path(path)
    if p.is_dir():
        files = sorted(f for f in p.iterdir() if f.is_file() and f.suffix.lower() in SUFFIXES)
        if len(files) != 1:
            found = [f.name for f in files]
            raise ValueError(
                f"{p}: expected exactly one .ply / .splat file in the folder, found {found}"
            )
        p = files[0]
    if max_gaussians is not None and (
        isinstance(max_gaussians, bool) or int(max_gaussians) != max_gaussians or max_gaussians < 1
    ):
        raise ValueError(f"max_gaussians must be a positive integer or None, got {max_gaussians!r}")
    gmap = GaussianMap.load(p)
    if max_gaussians is not None and gmap.num_gaussians > max_gaussians:
        gen = torch.Generator().manual_seed(int(seed))
        idx = torch.randperm(gmap.num_gaussians, generator=gen)[: int(max_gaussians)]
        gmap = gmap.subset(torch.sort(idx).values)
    return gmap
