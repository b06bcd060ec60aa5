"""``agilegs export SESSION OUT``: a session's acquired views as a dataset the field trains on,
and its map as a point cloud, read from a running server (``--server URL``) or offline from a
state folder (``--state-dir DIR``).

``OUT`` receives:

* ``images/<view id, 5 digits>.png`` (or ``.jpg``): each acquired view's image as it came
  (png and jpeg bytes unchanged; raw uint8 pixels as a lossless PNG; raw float pixels
  rounded to 8 bits); views without an image are left out;
* ``depth/<view id>.png``: its depth as a 16-bit PNG in thousandths of a scene unit (0:
  missing or beyond 65.535 units), the nerfstudio convention (``depth_unit_scale_factor``
  1e-3) that this project's loader reads with its default ``depth_scale`` 1000;
* ``transforms.json`` (``--format nerfstudio``): nerfstudio's layout, ``camera_model``
  ``PINHOLE``, per frame ``fl_x fl_y cx cy w h`` and ``transform_matrix`` (camera-to-world,
  OpenGL axes: the pose's y and z axes negated), ``depth_file_path``, and
  ``agilegs_view_id``; ``ns-train splatfacto --data OUT`` trains on it;
* ``sparse/0/cameras.txt``, ``images.txt``, ``points3D.txt`` (``--format colmap``): a COLMAP
  text model, one ``PINHOLE`` camera per distinct intrinsics, each image's world-to-camera
  pose (OpenCV axes, COLMAP's own), and the map's means as points (colour from the DC
  coefficient; no tracks); the original 3DGS ``train.py -s OUT`` and nerfstudio's
  ``colmap`` data parser read it.

With ``OUT`` a file ending in ``.ply`` or ``.splat``, the map alone is written there: the
Inria 3DGS ``.ply`` (float32, equal to the map) or the antimatter15 ``.splat``, as
``get_gaussians`` answers it. Both dataset formats by default. Numbers are written with every
digit (``repr``), so poses read back equal the session's to float64 rounding. Exit status 0 on
success, 2 when the session cannot be read (one line on stderr says why).
"""

from __future__ import annotations

import argparse
import io
import json
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from agilegs.client import AgileGSError, Client
from agilegs.schemas import FramesOut, GaussiansOut, Intrinsics
from agilegs.schemas.geometry import matrix_to_quaternion_xyzw

__all__ = ["FORMATS", "Exported", "add_arguments", "from_server", "from_state", "run",
           "write_dataset"]

FORMATS = ("nerfstudio", "colmap")
SH_C0 = 0.28209479177387814  # the zeroth spherical harmonic: colour = 0.5 + SH_C0 * dc
_SUFFIX = {"png": ".png", "jpeg": ".jpg", "raw": ".png"}
_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV camera axes <-> OpenGL camera axes


@dataclass(frozen=True)
class Exported:
    """What :func:`write_dataset` wrote: the images, the views left out (no image), the
    points of the COLMAP model."""

    images: int
    skipped: int
    points: int
    formats: tuple[str, ...]


def _image_file(frame_image: object, name: str) -> tuple[str, bytes]:
    """The image's file name (``name`` + its suffix) and bytes."""
    from agilegs.schemas import ImageData

    assert isinstance(frame_image, ImageData)
    if frame_image.encoding != "raw":
        return name + _SUFFIX[frame_image.encoding], frame_image.data
    from PIL import Image

    a = frame_image.to_numpy()
    if a.dtype != np.uint8:
        a = (np.clip(a, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(a)).save(buf, format="PNG")
    return name + ".png", buf.getvalue()


def _depth_png(depth: np.ndarray) -> bytes:
    """Depth [H, W] in scene units as a 16-bit PNG of thousandths (0: missing, or too far)."""
    from PIL import Image

    mm = np.rint(np.nan_to_num(depth.astype(np.float64), nan=0.0) * 1000.0)
    mm[(mm < 0) | (mm > 65535)] = 0
    buf = io.BytesIO()
    Image.fromarray(mm.astype(np.uint16)).save(buf, format="PNG")
    return buf.getvalue()


def _colours(gaussians: GaussiansOut) -> np.ndarray:
    sh = gaussians.arrays.sh.to_numpy()
    return np.rint(np.clip(0.5 + SH_C0 * sh[:, 0, :].astype(np.float64), 0, 1) * 255
                   ).astype(np.uint8)


def _num(x: float) -> str:
    return repr(float(x))


def write_dataset(out: str | Path, frames: FramesOut, gaussians: GaussiansOut | None = None,
                  formats: Sequence[str] = FORMATS) -> Exported:
    """Write ``frames`` (a ``get_frames`` answer, with depth or not) and the means of
    ``gaussians`` (the COLMAP model's points; none without it) to the folder ``out`` in
    ``formats`` (see the module docstring)."""
    unknown = sorted(set(formats) - set(FORMATS))
    if unknown or not formats:
        raise ValueError(f"formats must be among {', '.join(FORMATS)}, got {list(formats)}")
    out = Path(out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    ns_frames: list[dict[str, object]] = []
    cameras: dict[tuple[float, ...], int] = {}
    images_txt: list[str] = []
    skipped = 0
    for fr in frames.frames:
        v = fr.view
        if fr.image is None or v.intrinsics is None:
            skipped += 1
            continue
        stem = f"{v.id:05d}"
        name, data = _image_file(fr.image, stem)
        (out / "images" / name).write_bytes(data)
        k: Intrinsics = v.intrinsics
        c2w = v.pose.to_matrix()
        entry: dict[str, object] = {
            "file_path": f"images/{name}", "agilegs_view_id": v.id,
            "fl_x": k.fx, "fl_y": k.fy, "cx": k.cx, "cy": k.cy, "w": k.width, "h": k.height,
            "transform_matrix": (c2w @ _OPENGL).tolist()}
        if fr.depth is not None:
            (out / "depth").mkdir(exist_ok=True)
            (out / "depth" / f"{stem}.png").write_bytes(_depth_png(fr.depth.to_numpy()))
            entry["depth_file_path"] = f"depth/{stem}.png"
        ns_frames.append(entry)
        cam = cameras.setdefault((k.width, k.height, k.fx, k.fy, k.cx, k.cy), len(cameras) + 1)
        r = c2w[:3, :3].T  # world-to-camera
        t = -r @ c2w[:3, 3]
        q = np.roll(matrix_to_quaternion_xyzw(r), 1)  # COLMAP: w, x, y, z
        images_txt.append(" ".join([str(len(images_txt) // 2 + 1), *map(_num, q), *map(_num, t),
                                    str(cam), name]))
        images_txt.append("")  # no 2D points
    points = 0
    if "nerfstudio" in formats:
        doc = {"camera_model": "PINHOLE", "frames": ns_frames}
        (out / "transforms.json").write_text(json.dumps(doc, indent=2) + "\n")
    if "colmap" in formats:
        sparse = out / "sparse" / "0"
        sparse.mkdir(parents=True, exist_ok=True)
        cams = [f"{cid} PINHOLE {int(k[0])} {int(k[1])} " + " ".join(map(_num, k[2:]))
                for k, cid in cameras.items()]
        (sparse / "cameras.txt").write_text(
            "# Camera list with one line of data per camera:\n"
            "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
            f"# Number of cameras: {len(cams)}\n" + "".join(c + "\n" for c in cams))
        (sparse / "images.txt").write_text(
            "# Image list with two lines of data per image:\n"
            "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
            "#   POINTS2D[] as (X, Y, POINT3D_ID)\n"
            f"# Number of images: {len(images_txt) // 2}\n"
            + "".join(line + "\n" for line in images_txt))
        lines = []
        if gaussians is not None and gaussians.count:
            means = gaussians.arrays.means.to_numpy()
            rgb = _colours(gaussians)
            lines = [f"{i + 1} {_num(x)} {_num(y)} {_num(z)} {r} {g} {b} 0"
                     for i, ((x, y, z), (r, g, b)) in enumerate(zip(means.tolist(),
                                                                    rgb.tolist()))]
        points = len(lines)
        (sparse / "points3D.txt").write_text(
            "# 3D point list with one line of data per point:\n"
            "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
            f"# Number of points: {points}\n" + "".join(line + "\n" for line in lines))
    return Exported(images=len(ns_frames), skipped=skipped, points=points,
                    formats=tuple(f for f in FORMATS if f in formats))


def from_server(server: str | Client, session: str, *, token: str | None = None
                ) -> tuple[FramesOut, GaussiansOut]:
    """A session's frames (with depth) and Gaussians, read from the server at the URL
    ``server`` (or through the client ``server``)."""
    if not isinstance(server, str):
        return server.get_frames(session), server.get_gaussians(session)
    with Client(server, token=token, timeout=600) as c:
        return c.get_frames(session), c.get_gaussians(session)


def from_state(state_dir: str | Path, session: str, *, frames: bool = True
               ) -> tuple[FramesOut, GaussiansOut]:
    """The same, read offline from a server's state folder (it changes nothing there; no
    frames with ``frames`` false); ValueError when the session is missing or damaged."""
    from agilegs.schemas import FramesRequest

    from .sessions.session import Session, SessionEnv
    from .settings import Settings
    from .store.integrity import Damage
    from .store.write import SessionStore

    root = Path(state_dir)
    store = SessionStore(root, fsync=False)
    if not (store.session_dir(session) / "manifest.json").is_file():
        raise ValueError(f"{root}: no session {session!r} (agilegs store check {root} lists "
                         "them)")
    got = store.inspect(session)
    if isinstance(got, Damage):
        raise ValueError(f"session {session!r} is damaged: {got.reason()} (agilegs store "
                         f"repair {root})")
    env = SessionEnv(settings=Settings(state_dir=root, mapper=False), store=store,
                     tmp_dir=root / "tmp")
    s = Session(got, env)
    read = s.get_frames(FramesRequest()) if frames else FramesOut(frames=[], version=got.version)
    return read, s.get_gaussians()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("session", metavar="SESSION", help="the session's id")
    parser.add_argument("out", metavar="OUT", help="the folder to write the dataset to, or a "
                        "file ending in .ply (Inria 3DGS) or .splat for the map alone")
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument("--server", metavar="URL", help="a running server, e.g. "
                                                       "http://127.0.0.1:8000")
    where.add_argument("--state-dir", metavar="DIR", help="a server's state folder (offline)")
    parser.add_argument("--token", help="the server's bearer token (AGILEGS_TOKEN), if any")
    parser.add_argument("--format", choices=[*FORMATS, "both"], default="both",
                        help="transforms.json (nerfstudio), a COLMAP text model, or both "
                             "(default)")


def run(args: argparse.Namespace) -> int:
    fmt = Path(args.out).suffix.lower().lstrip(".")
    try:
        if fmt in ("ply", "splat"):
            return _save_map(args, Path(args.out), fmt)
        if args.server:
            frames, gaussians = from_server(args.server, args.session, token=args.token)
        else:
            frames, gaussians = from_state(args.state_dir, args.session)
    except (AgileGSError, ValueError, OSError) as exc:
        sys.stderr.write(f"agilegs export: {exc}\n")
        return 2
    formats = FORMATS if args.format == "both" else (args.format,)
    done = write_dataset(args.out, frames, gaussians, formats)
    sys.stdout.write(f"agilegs export: {done.images} views of {args.session} to {args.out} "
                     f"({' and '.join(done.formats)}; {done.points} points)"
                     + (f"; {done.skipped} views without an image left out" if done.skipped
                        else "") + "\n")
    return 0


def _save_map(args: argparse.Namespace, out: Path, fmt: str) -> int:
    """The session's map as the file ``out`` (.ply or .splat)."""
    if args.server:
        with Client(args.server, token=args.token, timeout=600) as c:
            c.save_gaussians(args.session, out)
        count = None
    else:
        from .errors import ServiceError
        from .sessions.convert import gaussians_file

        gaussians = from_state(args.state_dir, args.session, frames=False)[1]
        try:
            out.write_bytes(gaussians_file(gaussians, fmt))
        except ServiceError as exc:
            raise ValueError(exc.message) from None
        count = gaussians.count
    sys.stdout.write(f"agilegs export: the map of {args.session} to {out}"
                     + (f" ({count} Gaussians)" if count is not None else "") + "\n")
    return 0
