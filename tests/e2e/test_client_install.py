"""The client SDK as a robot installs it: importing it loads neither torch nor the server; the
wheel ``python -m build --wheel`` makes holds the package and the demo's two scenes but not
the benchmark's; installed with its ``zenoh`` extra into a fresh virtual environment it brings
no torch, its CLI answers ``--help`` and says what a server command needs, and it runs a
robot's calls against a server; installing from the repository's git URL gives the same
package. The builds and installs are in the heavy lane (``pytest -m heavy``, run by
``.ci/run``)."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
from conftest import ROOT, ServerProcess

#: what a wheel is built from (README, pyproject and the packages' folders)
SOURCES = ("pyproject.toml", "README.md", "config", "schemas", "client", "service", "lab")

ROBOT = """
import sys
import numpy as np
from agilegs.client import Client, ZenohClient

pool = np.tile(np.eye(4), (3, 1, 1))
pool[:, 2, 3] = [-2.0, -2.5, -3.0]   # three poses on the -z axis, looking at the origin
with Client(sys.argv[1]) as c:
    c.create_session({"fx": 30, "fy": 30, "cx": 16, "cy": 16, "width": 32, "height": 32},
                     id="robot", bounds={"min": [-0.5] * 3, "max": [0.5] * 3},
                     init_gaussians=60, pool=pool)
    d = c.select("robot", method="agile", commit=True)
    print("chosen", d.chosen.id)
print("torch" in sys.modules, ZenohClient.__name__)
"""


def test_import_does_not_load_torch() -> None:
    code = ("import sys, agilegs.client, agilegs.schemas; "
            "from agilegs.client import Client, AsyncClient, ZenohClient; "
            "bad = [m for m in ('torch', 'fastapi', 'uvicorn') if m in sys.modules]; "
            "print(bad); sys.exit(1 if bad else 0)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stdout + out.stderr


def _run(cmd: list[str], timeout: float = 300, **kw: object) -> subprocess.CompletedProcess[str]:
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, **kw)  # type: ignore[call-overload]
    assert done.returncode == 0, f"{cmd}:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    return done  # type: ignore[no-any-return]


def _fresh_venv(where: Path) -> Path:
    """A new virtual environment without this one's packages; its python."""
    _run([sys.executable, "-m", "venv", str(where)])
    return where / "bin" / "python"


def _check_client_only(py: Path, tmp_path: Path) -> None:
    """``py``'s environment has the client and no torch; its CLI answers; it runs a robot's
    calls against a server of this environment."""
    missing = _run([str(py), "-c", "import importlib.util as u; "
                    "print([m for m in ('torch', 'fastapi', 'matplotlib') if u.find_spec(m)])"])
    assert missing.stdout.strip() == "[]"
    agilegs = str(py.parent / "agilegs")
    assert "serve" in _run([agilegs, "--help"], timeout=60).stdout
    served = subprocess.run([agilegs, "serve"], capture_output=True, text=True, timeout=60)
    assert served.returncode == 2 and "pip install" in served.stderr, served.stderr
    with ServerProcess(tmp_path / "state", zenoh=False) as srv:
        out = _run([str(py), "-c", ROBOT, srv.url], timeout=120).stdout.split()
    assert out[0] == "chosen" and out[2:] == ["False", "ZenohClient"], out


@pytest.mark.heavy  # a build and an install from the package index: tens of seconds
@pytest.mark.timeout(600)
def test_the_wheel_installs_the_client_without_torch(tmp_path: Path) -> None:
    src = tmp_path / "src"
    src.mkdir()
    for name in SOURCES:
        (shutil.copytree if (ROOT / name).is_dir() else shutil.copy)(ROOT / name, src / name)
    built = _run([sys.executable, "-m", "build", "--wheel", "--outdir", str(tmp_path / "dist"),
                  str(src)], timeout=400)
    assert "WARNING" not in built.stdout + built.stderr  # setuptools' deprecations, packages
    wheel = next((tmp_path / "dist").glob("agilegs-*-py3-none-any.whl"))
    names = zipfile.ZipFile(wheel).namelist()
    for package in ("agilegs/client/", "agilegs/schemas/", "agilegs/service/nbv/"):
        assert any(n.startswith(package) for n in names), package
    scenes = sorted(n for n in names if n.endswith((".splat", ".ply", ".png")))
    assert scenes == ["agilegs/lab/scenes/spot/spot_10k.splat",
                      "agilegs/lab/scenes/teapot/teapot_10k.splat"], scenes
    assert wheel.stat().st_size < 2 * 2**20  # the benchmark's 9 MB of scenes stay out
    py = _fresh_venv(tmp_path / "robot")
    _run([str(py), "-m", "pip", "install", "-q", f"{wheel}[zenoh]"], timeout=400)
    _check_client_only(py, tmp_path)


@pytest.mark.heavy
@pytest.mark.timeout(900)
def test_the_git_url_installs_the_client_without_torch(tmp_path: Path) -> None:
    if not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    repo = tmp_path / "repo"  # the checkout's last commit, as a repository of one commit
    _run(["git", "clone", "-q", "--depth", "1", f"file://{ROOT}", str(repo)])
    shutil.rmtree(repo / ".git")  # (pip loops on a shallow clone's refs)
    git = ["git", "-C", str(repo), "-c", "user.name=test", "-c", "user.email=test@localhost"]
    for step in (["init", "-q"], ["add", "-A"], ["commit", "-q", "-m", "the checkout"]):
        _run([*git, *step])
    py = _fresh_venv(tmp_path / "robot")
    # pip takes a file URL with a host part only ("git+file:///..." is refused)
    _run([str(py), "-m", "pip", "install", "-q",
          f"agilegs[zenoh] @ git+file://localhost{repo}"], timeout=600)
    _check_client_only(py, tmp_path)
