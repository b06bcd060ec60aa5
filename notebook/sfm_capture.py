"""Make a benchmark capture from a folder of photographs: structure from motion with pycolmap.

Used for the captures of service/data/scenes/ made from unposed photograph sets (each scene's
README gives the command). pycolmap is a tool for preparing data, not a dependency of the
project: ``pip install pycolmap`` (4.2.1 made the scenes) in an environment of your own.

    python notebook/sfm_capture.py SRC_DIR OUT_DIR [--sfm-size 480] [--size 240]
        [--every 1] [--matcher exhaustive|sequential] [--mapper incremental|global]
        [--features 4096] [--no-refine-distortion] [--threads 2]

1. Every ``--every``-th photograph of SRC_DIR (sorted by name: the capture order), its EXIF
   orientation applied, is resized to ``--sfm-size`` pixels on its longest side (PIL LANCZOS)
   and SIFT features are extracted (CPU) with one SIMPLE_RADIAL camera shared by all.
2. Pairs are matched (exhaustive, or sequential with loop detection off for long sets) and
   geometrically verified; COLMAP's incremental (or global) mapper builds the model; the
   largest model is kept.
3. The photographs are written at ``--size`` pixels on the longest side (a factor
   size / sfm-size of the SfM images, so the camera is rescaled by that exact factor) as JPEG
   quality 90 in OUT_DIR/images/, and the model as COLMAP text in OUT_DIR/sparse/0/
   (cameras.txt, images.txt with the rescaled 2-D observations, points3D.txt). Photographs
   the mapper did not register are left out.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from pathlib import Path

import pycolmap
from PIL import Image, ImageOps


def resize(src: Path, dst: Path, longest: int) -> tuple[int, int]:
    """Write src resized to ``longest`` pixels on its longest side; returns (width, height)."""
    im = ImageOps.exif_transpose(Image.open(src)).convert("RGB")
    s = longest / max(im.size)
    size = (round(im.size[0] * s), round(im.size[1] * s))
    im.resize(size, Image.Resampling.LANCZOS).save(dst, quality=90)
    return size


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("src", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--sfm-size", type=int, default=480)
    ap.add_argument("--size", type=int, default=240)
    ap.add_argument("--every", type=int, default=1)
    ap.add_argument("--matcher", choices=("exhaustive", "sequential"), default="exhaustive")
    ap.add_argument("--mapper", choices=("incremental", "global"), default="incremental")
    ap.add_argument("--features", type=int, default=4096)
    ap.add_argument("--no-refine-distortion", action="store_true",
                    help="keep the distortion at zero in bundle adjustment (narrow lenses)")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()

    exts = {".jpg", ".jpeg", ".png"}
    photos = sorted(p for p in args.src.iterdir() if p.suffix.lower() in exts)[:: args.every]
    work = Path(tempfile.mkdtemp(prefix="sfm_"))
    (work / "images").mkdir()
    for p in photos:
        resize(p, work / "images" / (p.stem + ".jpg"), args.sfm_size)
    db = work / "database.db"
    ext = pycolmap.FeatureExtractionOptions(num_threads=args.threads)
    ext.sift.max_num_features = args.features
    pycolmap.extract_features(db, work / "images", camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=pycolmap.ImageReaderOptions(
                                  camera_model="SIMPLE_RADIAL"),
                              extraction_options=ext, device=pycolmap.Device.cpu)
    match = pycolmap.FeatureMatchingOptions(num_threads=args.threads)
    if args.matcher == "exhaustive":
        pycolmap.match_exhaustive(db, matching_options=match, device=pycolmap.Device.cpu)
    else:
        pycolmap.match_sequential(db, matching_options=match,
                                  pairing_options=pycolmap.SequentialPairingOptions(overlap=12),
                                  device=pycolmap.Device.cpu)
    if args.mapper == "global":
        gopts = pycolmap.GlobalPipelineOptions(num_threads=args.threads)
        models = pycolmap.global_mapping(db, work / "images", work / "sparse", options=gopts)
    else:
        opts = pycolmap.IncrementalPipelineOptions(num_threads=args.threads)
        opts.ba_refine_extra_params = not args.no_refine_distortion
        models = pycolmap.incremental_mapping(db, work / "images", work / "sparse",
                                              options=opts)
    rec = max(models.values(), key=lambda r: r.num_reg_images())
    sys.stdout.write(f"{len(photos)} photographs, {len(models)} model(s); the largest "
                     f"registers {rec.num_reg_images()} with {rec.num_points3D()} points\n")

    out_images = args.out / "images"
    model_dir = args.out / "sparse" / "0"
    out_images.mkdir(parents=True, exist_ok=True)
    model_dir.mkdir(parents=True, exist_ok=True)
    scale = args.size / args.sfm_size
    for cam in rec.cameras.values():
        w, h = cam.width, cam.height
        cam.rescale(round(w * scale), round(h * scale))
    for image in rec.images.values():
        if not image.has_pose:
            continue
        size = resize(work / "images" / image.name, out_images / image.name, args.size)
        cam = rec.cameras[image.camera_id]
        assert size == (cam.width, cam.height), (image.name, size, cam.width, cam.height)
        for p2d in image.points2D:
            p2d.xy = p2d.xy * scale
    rec.write_text(model_dir)
    compact(model_dir)
    shutil.rmtree(work)


def compact(model_dir: Path) -> None:
    """Keep in images.txt only the 2-D points that observe a 3-D point (most keypoints do
    not), renumbering the tracks of points3D.txt to match: the same model, a fifth the size."""
    images = (model_dir / "images.txt").read_text().splitlines()
    remap: dict[tuple[int, int], int] = {}
    body = [ln for ln in images if not ln.startswith("#")]
    out = [ln for ln in images if ln.startswith("#")]
    for head, pts in zip(body[0::2], body[1::2], strict=True):
        image_id = int(head.split()[0])
        v = pts.split()
        kept = []
        for idx in range(len(v) // 3):
            if int(v[3 * idx + 2]) != -1:
                remap[(image_id, idx)] = len(kept)
                kept.append(" ".join(v[3 * idx:3 * idx + 3]))
        out += [head, " ".join(kept)]
    (model_dir / "images.txt").write_text("\n".join(out) + "\n")
    lines = []
    for ln in (model_dir / "points3D.txt").read_text().splitlines():
        if ln.startswith("#"):
            lines.append(ln)
            continue
        v = ln.split()
        track = [f"{v[k]} {remap[(int(v[k]), int(v[k + 1]))]}" for k in range(8, len(v), 2)]
        lines.append(" ".join(v[:8] + track))
    (model_dir / "points3D.txt").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
