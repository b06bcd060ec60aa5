"""The benchmark's scenes in ``lab/scenes/``: every file intact (its sha256 in the
scene's meta.json), the licence and attribution of every scene listed in its README.md as its
meta.json says (``python tests/lab/bench/test_scenes_folder.py`` prints the rows), and none but the
demo's two in the wheel (tests/e2e/test_client_install.py builds one)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from agilegs.lab.bench.scenes import detect_scene_kind

ROOT = Path(__file__).resolve().parents[3]
SCENES = ROOT / "lab" / "scenes"

OBJECTS = ("bob", "boot", "fish", "koala", "penguin", "skull", "spot", "stanford_bunny",
           "teapot", "violin")
"""The benchmark's splat objects (docs/benchmarks.md); with the capture (plant) and the posed
scene (floor), its twelve scenes."""

CAPTURES = ("buddha", "skull_photos", "brighton_beach", "tankard", "flowerpot", "caliterra")
"""Real captures (photographs with poses), each with its licence file and README."""


def meta(scene: str) -> dict:
    return json.loads((SCENES / scene / "meta.json").read_text(encoding="utf-8"))


def attribution(m: dict) -> str:
    return m.get("attribution") or f"“{m['title']}” by {m['author']}, {m['license']}."


def rows() -> list[str]:
    """The README's row of every splat scene, from its meta.json."""
    out = []
    for scene in sorted(p.parent.name for p in SCENES.glob("*/meta.json")):
        m = meta(scene)
        files = sorted(f.name for f in (SCENES / scene).glob("*.splat"))
        count = sum((SCENES / scene / f).stat().st_size // 32 for f in files)
        out.append(f"| `{scene}` | {m['source_method']} | {', '.join(f'`{f}`' for f in files)} "
                   f"| {count:,} | {m['license']} | {attribution(m)} |")
    return out


def test_the_twelve_scenes_are_here_and_intact() -> None:
    assert sorted(p.name for p in SCENES.iterdir() if p.is_dir()) == sorted(
        (*OBJECTS, "plant", "floor", *CAPTURES))
    for scene in (*OBJECTS, "plant"):
        m = meta(scene)
        digests = {lod["file"]: lod["sha256"] for lod in m.get("lods", [])}
        digests[m["file"]] = m["sha256"]
        files = list((SCENES / scene).glob("*.splat"))
        assert len(files) == 1, files  # the level of detail the benchmark uses
        for f in files:
            assert hashlib.sha256(f.read_bytes()).hexdigest() == digests[f.name], f
        assert detect_scene_kind(SCENES / scene) == "splat"
    assert detect_scene_kind(SCENES / "floor") == "transforms"
    frames = json.loads((SCENES / "floor" / "transforms_train.json").read_text())["frames"]
    for frame in frames:  # every image and depth map the set names is here
        for key in ("file_path", "depth_file_path"):
            path = SCENES / "floor" / frame[key]
            assert path.is_file() or path.with_suffix(".png").is_file(), path
    for scene in CAPTURES:
        assert detect_scene_kind(SCENES / scene) == "colmap"
        assert (SCENES / scene / "LICENSE.md").is_file()
        assert (SCENES / scene / "README.md").is_file()
        text = (SCENES / scene / "sparse" / "0" / "images.txt").read_text()
        body = [ln for ln in text.splitlines() if not ln.startswith("#")]
        names = [ln.split()[-1] for ln in body[0::2]]  # IMAGE_ID ... NAME, then its POINTS2D
        assert names and all((SCENES / scene / "images" / n).is_file() for n in names)


def test_the_readme_credits_every_scene_as_its_meta_says() -> None:
    text = (SCENES / "README.md").read_text(encoding="utf-8")
    for row in rows():
        assert row in text, f"lab/scenes/README.md lacks the row:\n{row}"
    assert "Marcel Padilla" in text and "zlib" in text and "pybullet" in text
    # the demo's scenes are the benchmark's folders
    from agilegs.lab.scenes import bundled_scene

    for name in ("spot", "teapot"):
        assert bundled_scene(name) == SCENES / name / f"{name}_10k.splat"

if __name__ == "__main__":
    print("\n".join(rows()))
