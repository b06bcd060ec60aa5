"""Schemathesis hooks for agilegs (``SCHEMATHESIS_HOOKS=schemathesis_hooks`` with this folder on
``PYTHONPATH``; the suite's fuzz test loads them the same way).

* msgpack both ways: request bodies are packed (integers beyond 64 bits, which only
  schema-violating data holds, travel as strings), responses unpacked with their bytes as
  base64 text, which is how the schema describes them in JSON.
* Positive cases meet the rules that JSON Schema cannot state, which the schema names in its
  ``x-agilegs-rules`` extension and the field descriptions spell out: a pose's rotation is
  orthonormal (the generated block is replaced by its nearest rotation) and a quaternion unit;
  bounds have ``min < max``; an array's bytes match its dtype and shape; an image or depth map
  matches its intrinsics and decodes; uploaded Gaussians (in a body or as the raw body of
  ``set_gaussians``) are a readable file or consistent arrays; a pool's ``ids`` name one id per pose; a
  select's ``targets`` come with ``config.objective = "target"``; width x height stays within the pixel limit
  (here at most :data:`SIDE` per side, which also keeps the fuzzed selections cheap).
  Positive cases create sessions on the server under test, with Gaussians: they drop
  ``?instance=``, whose valid values are the ids of a cluster's live instances, and a creation
  that would give the map none gets bounds, and one without a pool gets four candidates (so
  that later stateful steps can select). Negative cases are left exactly as
  generated.
* A link that gives the whole request body (``x-schemathesis: {merge_body: false}``: the
  chosen candidate to ``commit``, a committed view to ``add_observations``) makes a case
  without a media type, and schemathesis (4.x) then asks the target operation for its only
  one; the document states two, JSON and msgpack, both valid, so it raised "Can not detect
  appropriate media type" and ended the stateful phase. Such a case goes as JSON
  (:func:`_default_media_type`); any other case keeps the type schemathesis chose.
"""

from __future__ import annotations

import base64
import io
import itertools
import math
from typing import Any

import msgpack
import numpy as np
import schemathesis
from schemathesis import GenerationMode


def _patch_default_media_type() -> None:
    from schemathesis.schemas import APIOperation

    original = APIOperation._get_default_media_type

    def _default_media_type(self: Any) -> str:
        types = self.get_request_payload_content_types()
        if len(types) > 1 and "application/json" in types:
            return "application/json"
        return str(original(self))

    APIOperation._get_default_media_type = _default_media_type  # type: ignore[method-assign]


_patch_default_media_type()

RAW_TYPES = ("application/octet-stream", "application/x-ply", "application/x-splat")
"""Media types of a raw Gaussians upload (``set_gaussians``)."""

SIDE = 12
"""Largest image side of a repaired positive case (pixels)."""


# ---------------------------------------------------------------------------- msgpack
def _packable(value: Any) -> Any:
    if isinstance(value, int) and not isinstance(value, bool) and not -2**63 <= value < 2**64:
        return str(value)
    if isinstance(value, list):
        return [_packable(v) for v in value]
    if isinstance(value, dict):
        return {k: _packable(v) for k, v in value.items()}
    return value


def _as_json_types(value: Any) -> Any:
    if isinstance(value, bytes):
        return base64.b64encode(value).decode("ascii")
    if isinstance(value, list):
        return [_as_json_types(v) for v in value]
    if isinstance(value, dict):
        return {k: _as_json_types(v) for k, v in value.items()}
    return value


@schemathesis.serializer("application/msgpack")
def _pack(ctx: Any, value: Any) -> bytes:
    return msgpack.packb(_packable(value), use_bin_type=True)


@schemathesis.deserializer("application/msgpack")
def _unpack(ctx: Any, response: Any) -> Any:
    return _as_json_types(msgpack.unpackb(response.content, raw=False))


# ---------------------------------------------------------------------------- repairs
def _b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


def _rotation(block: list[list[float]]) -> np.ndarray:
    """The proper rotation nearest ``block`` [3, 3] (the identity for a degenerate one)."""
    a = np.nan_to_num(np.asarray(block, dtype=np.float64), nan=0.0, posinf=1.0, neginf=-1.0)
    u, s, vt = np.linalg.svd(a)
    if s.min() < 1e-6:
        return np.eye(3)
    r = u @ vt
    if np.linalg.det(r) < 0:
        u[:, -1] *= -1
        r = u @ vt
    return r


def _fix_pose(p: dict[str, Any]) -> None:
    m = p.get("matrix")
    if isinstance(m, list) and len(m) == 4:
        r = _rotation([row[:3] for row in m[:3]])
        for i in range(3):
            m[i] = [float(r[i, 0]), float(r[i, 1]), float(r[i, 2]), float(m[i][3])]
        m[3] = [0.0, 0.0, 0.0, 1.0]
    q = p.get("orientation_xyzw")
    if isinstance(q, list) and len(q) == 4:
        n = math.sqrt(sum(v * v for v in q))
        p["orientation_xyzw"] = [v / n for v in q] if n > 1e-3 else [0.0, 0.0, 0.0, 1.0]


def _fix_bounds(b: dict[str, Any]) -> None:
    lo, hi = b["min"], b["max"]
    for i in range(3):
        a, c = sorted((lo[i], hi[i]))
        if not a < c:
            a, c = (a - 1.0, a) if a > 0 else (a, a + 1.0)
        lo[i], hi[i] = a, c


def _fix_intrinsics(k: dict[str, Any]) -> tuple[int, int]:
    k["width"], k["height"] = int(min(k["width"], SIDE)), int(min(k["height"], SIDE))
    return k["height"], k["width"]


def _image(encoding: str, dtype: str | None, h: int, w: int) -> dict[str, Any]:
    if encoding == "raw":
        dt = np.dtype(dtype or "uint8").newbyteorder("<")
        return {"encoding": "raw", "dtype": dt.name, "shape": [h, w, 3],
                "data": _b64(np.full((h, w, 3), 0.5 if dt.kind == "f" else 128, dt).tobytes())}
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.full((h, w, 3), 128, np.uint8)).save(
        buf, format="PNG" if encoding == "png" else "JPEG")
    return {"encoding": encoding, "data": _b64(buf.getvalue())}


def _fix_observation(o: dict[str, Any]) -> None:
    if o.get("image") is None and o.get("depth") is None:
        return
    if o.get("intrinsics") is None:
        o["intrinsics"] = {"fx": 10.0, "fy": 10.0, "cx": 4.0, "cy": 4.0, "width": 8, "height": 8}
    h, w = _fix_intrinsics(o["intrinsics"])
    if isinstance(o.get("image"), dict):
        img = o["image"]
        o["image"] = _image(img.get("encoding", "raw"), img.get("dtype"), h, w)
    if isinstance(o.get("depth"), dict):
        dt = np.dtype(o["depth"].get("dtype", "float32")).newbyteorder("<")
        o["depth"] = {"dtype": dt.name, "shape": [h, w], "data": _b64(np.ones((h, w), dt).tobytes())}


def _gaussian_arrays(n: int) -> dict[str, Any]:
    rng = np.random.default_rng(n)
    arrays = {"means": rng.uniform(-0.5, 0.5, (n, 3)), "log_scales": np.full((n, 3), -3.0),
              "quats": np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)), "opacity_logits": np.zeros(n),
              "sh": np.zeros((n, 1, 3))}
    return {k: {"dtype": "float32", "shape": list(v.shape),
                "data": _b64(v.astype("<f4").tobytes())} for k, v in arrays.items()}


def _fix_gaussians(g: dict[str, Any]) -> None:
    n = 20
    if g.get("format") == "arrays":
        g["arrays"] = _gaussian_arrays(n)
        return
    import tempfile
    from pathlib import Path

    from agilegs.service.nbv import GaussianMap

    gmap = GaussianMap(**_decoded(_gaussian_arrays(n)))
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"g.{g['format']}"
        gmap.save(path)
        g["data"] = _b64(path.read_bytes())


def _decoded(arrays: dict[str, Any]) -> dict[str, Any]:
    import torch

    return {k: torch.from_numpy(np.frombuffer(base64.b64decode(v["data"]), "<f4")
                                .reshape(v["shape"]).copy()) for k, v in arrays.items()}


def _gaussians_file(fmt: str) -> bytes:
    g = {"format": fmt}
    _fix_gaussians(g)
    return base64.b64decode(g["data"])


def _fix_pool(p: dict[str, Any]) -> None:
    ids = p.get("ids")
    if isinstance(ids, list):
        n = len(p["poses"])
        kept = ids[:n]
        fresh = (i for i in range(2**20) if i not in set(kept))
        p["ids"] = kept + [next(fresh) for _ in range(n - len(kept))]


def repair(value: Any) -> None:
    """Make positive data meet the rules JSON Schema cannot state (in place)."""
    if isinstance(value, list):
        for v in value:
            repair(v)
        return
    if not isinstance(value, dict):
        return
    for v in value.values():
        repair(v)
    keys = set(value)
    if keys and keys <= {"matrix", "position", "orientation_xyzw"}:
        _fix_pose(value)
    elif keys == {"min", "max"}:
        _fix_bounds(value)
    elif {"fx", "fy", "cx", "cy", "width", "height"} <= keys:
        _fix_intrinsics(value)
    elif "format" in keys and ("data" in keys or "arrays" in keys):
        _fix_gaussians(value)
    elif isinstance(value.get("poses"), list):
        _fix_pool(value)
    if keys & {"pose", "candidate_id", "view_id"} or "depth" in keys or "image" in keys:
        _fix_observation(value)
    if isinstance(value.get("targets"), list):  # a select's targets need the target objective
        if not isinstance(value.get("config"), dict):
            value["config"] = {}
        value["config"]["objective"] = "target"


_CREATED = itertools.count()


def _fresh_id(body: Any) -> None:
    """A session's creation body with an id gets one no earlier case used (hypothesis may
    repeat a generated id in every scenario, and all but the first would only meet 409)."""
    if isinstance(body, dict) and isinstance(body.get("id"), str):
        suffix = f"-{next(_CREATED)}"
        body["id"] = body["id"][:64 - len(suffix)] + suffix


def _with_gaussians(body: Any) -> None:
    """A session's creation body that gives the map no Gaussians (no upload, no depth frame,
    no bounds, or none of them asked for) gets bounds and a few: another valid body, whose
    session later steps can select on. One that asks for a Gaussian per depth pixel
    (``init_gaussians`` 0), whose count no schema bounds, asks for a few instead."""
    if not isinstance(body, dict) or body.get("gaussians") is not None:
        return
    frames = body.get("frames") or []
    if any(isinstance(f, dict) and f.get("depth") is not None for f in frames):
        if body.get("init_gaussians") == 0:  # one per depth pixel: may pass max_gaussians
            body["init_gaussians"] = 50
        return
    if body.get("bounds") is None:
        body["bounds"] = {"min": [-1.0, -1.0, -1.0], "max": [1.0, 1.0, 1.0]}
    if body.get("init_gaussians", 1) == 0:
        body["init_gaussians"] = 50


def _with_pool(body: Any) -> None:
    """A session's creation body without a pool gets four candidates on a ring around the
    origin, facing it: another valid body, on whose session a selection can answer (and
    whose chosen candidate the links carry on to a commit or an observation)."""
    if not isinstance(body, dict) or body.get("pool") is not None:
        return
    poses = []
    for k in range(4):
        a = k * math.pi / 2
        eye = np.array([3.0 * math.cos(a), 3.0 * math.sin(a), 0.5])
        z = -eye / np.linalg.norm(eye)  # looks at the origin (camera +z forward)
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        m = np.eye(4)
        m[:3, :3] = np.stack([x, y, z], axis=1)
        m[:3, 3] = eye
        poses.append({"matrix": m.tolist()})
    body["pool"] = {"poses": poses}


@schemathesis.hook
def map_case(ctx: Any, case: Any) -> Any:
    meta = case.meta
    if meta is not None and meta.generation.mode == GenerationMode.POSITIVE:
        if case.media_type in RAW_TYPES:  # a raw .ply / .splat upload
            fmt = (case.query or {}).get("format") or "splat"
            case.body = _gaussians_file(fmt if fmt in ("ply", "splat") else "splat")
        else:
            repair(case.body)
            if case.method.upper() == "POST" and case.path == "/v1/sessions":
                _with_gaussians(case.body)
                _with_pool(case.body)
                _fresh_id(case.body)
        if isinstance(case.query, dict):
            # ?instance= places a session on a cluster's instance: only the live instances' ids
            # are valid (404 instance_unavailable otherwise); positive cases use this server
            case.query.pop("instance", None)
    return case
