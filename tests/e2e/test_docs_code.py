"""Every code block of the README and docs/ runs as written.

The blocks are read from the pages (``python`` and ``bash`` fences; ``text``, ``json`` and
``toml`` fences are data). A block runs unless :data:`HOW` says otherwise for it, and says
why:

- ``server``: against the README's own ``agilegs serve`` command, started here (the README's
  block ``agilegs serve --host 127.0.0.1 --port 8000 ...``).
- ``state``: in a folder whose ``./agilegs-state`` holds a session and no server.
- ``parse``: a benchmark or a deployment too long or too big to run here: the block runs in
  bash with ``agilegs`` (and the commands named) replaced by a stand-in that parses the
  command line with the real parser (every option exists and takes the value given) and
  checks that every ``--scene`` it names is there.
- ``ci``: the set-up line of the README, which must be the one ``.ci/run`` runs.
- ``skip``: needs what CI has not (Docker, the PyTorch wheel index).

What stays the same everywhere but must differ on a shared machine: the HTTP port 8000, the
Zenoh endpoint 7447 and the page port 8080 become free ports, ``./agilegs-state`` a temporary
folder (:func:`substitute`). The lab notebook (``notebook/``) is left out: its dated pages
record commands as they ran at their commit. Every relative link of these pages, the
notebook's and the scenes' READMEs resolves, to a file and, for a page, to a heading.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shlex
import stat
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from conftest import ROOT, SMALL_INTRINSICS, free_port, ring_poses

from agilegs.service.launch import wait_until

PAGES = ["README.md", *sorted(str(p.relative_to(ROOT)) for p in (ROOT / "docs").glob("*.md"))]
CODE = ("python", "bash")


@dataclass(frozen=True)
class Block:
    page: str
    line: int
    lang: str
    text: str

    @property
    def key(self) -> tuple[str, str]:
        return self.page, self.text.splitlines()[0]

    def __str__(self) -> str:
        return f"{self.page}:{self.line}"


@dataclass(frozen=True)
class How:
    mode: str  # server, state, parse, ci, skip
    why: str = ""
    stand_ins: tuple[str, ...] = ()  # parse: more commands replaced by a recording no-op
    env: tuple[tuple[str, str], ...] = ()  # parse: variables an earlier block of the page set


BENCH = How("parse", "hours of CPU (the full tables); the page sets S=lab/scenes first",
            env=(("S", "lab/scenes"),))
HOW: dict[tuple[str, str], How] = {
    ("README.md", "python3 -m venv .venv && . .venv/bin/activate && pip install -q "
     "torch==2.13.0 && pip install -q -e \".[service,lab,dev]\" && agilegs demo"):
        How("ci", "the set-up is .ci/run's (this suite runs after it); the demo itself runs in "
                  "tests/e2e/test_demo.py"),
    ("README.md", "python3 -m venv .venv && . .venv/bin/activate && pip install -q "
     "torch==2.13.0 && pip install -q -e \".[service,lab,dev]\" && python -m pytest -q"):
        How("ci", "the suite itself, as .ci/run runs it"),
    ("README.md", "agilegs serve --host 127.0.0.1 --port 8000 --state-dir ./agilegs-state   "
     "# HTTP + Zenoh"): How("server", "the server the README's clients talk to"),
    ("README.md", "import json"): How("server"),
    ("docs/your-data.md", "agilegs export room room.ply --server http://127.0.0.1:8000       "
     "# the map"): How("server", "exports the session the block before made"),
    ("docs/server.md", "curl -s -o /dev/null -X DELETE http://127.0.0.1:8000/v1/sessions/box     "
     "# a fresh session"): How("server"),
    ("docs/viewer.md", "from agilegs.client import Client"): How("server"),
    ("docs/viewer.md", "pip install \"agilegs[viewer]\"          # viser, and no torch (the dev "
     "extra includes it)"):
        How("parse", "an install and servers that run until stopped", stand_ins=("pip",)),
    ("docs/server.md", "agilegs serve --host 127.0.0.1 --port 8000 --state-dir ./agilegs-state"
     "   # HTTP + Zenoh (tcp/127.0.0.1:7447)"):
        How("parse", "four alternative servers, each running until stopped"),
    ("docs/store.md", "agilegs store check ./agilegs-state             # changes nothing; exit "
     "1 if a session is damaged"): How("state"),
    ("docs/deploy.md", "python3 -m venv /opt/agilegs && . /opt/agilegs/bin/activate"):
        How("skip", "installs into /opt from the PyTorch wheel index, which CI cannot reach "
                    "(installs from a checkout and a wheel: tests/e2e/test_client_install.py)"),
    ("docs/deploy.md", "export AGILEGS_TOKEN=$(openssl rand -hex 32)"):
        How("parse", "a server for other machines (0.0.0.0), running until stopped"),
    ("docs/deploy.md", "docker build -f deploy/Dockerfile -t agilegs:cpu ."):
        How("skip", "needs a Docker daemon and a base image (the Dockerfile's commands: "
                    "tests/e2e/test_deploy_files.py)"),
    ("docs/deploy.md", "docker build -f deploy/Dockerfile -t agilegs:cuda --build-arg "
     "BASE=nvidia/cuda:12.8.1-runtime-ubuntu24.04 --build-arg TORCH_INDEX=https://download."
     "pytorch.org/whl/cu128 ."): How("skip", "needs Docker and a GPU"),
    ("docs/deploy.md", "export AGILEGS_TOKEN=$(openssl rand -hex 32) "
     "MINIO_ROOT_PASSWORD=$(openssl rand -hex 16)"):
        How("skip", "needs a Docker daemon (the compose file: tests/e2e/test_deploy_files.py)"),
    ("docs/benchmarks.md", "OMP_NUM_THREADS=1 agilegs bench fleet --sessions 10 --kills 20 "
     "--json fleet.json"):
        How("parse", "three servers killed twenty times, minutes (the fleet on loopback: "
                     "tests/e2e/test_fleet.py)"),
    ("docs/deploy.md", "export AWS_ACCESS_KEY_ID=... AWS_SECRET_ACCESS_KEY=... "
     "AWS_REGION=us-east-1"):
        How("parse", "an instance of a fleet on a lab's object store and router, running until "
                     "stopped (a fleet on loopback: tests/e2e/test_fleet.py)"),
    ("docs/deploy.md", "pip install -e '.[service,cuda]'"):
        How("skip", "needs an NVIDIA GPU and CUDA torch (the setting without CUDA: "
                    "tests/sessions/test_device.py)"),
    ("docs/gpu.md", "pip install torch --index-url https://download.pytorch.org/whl/cu128"):
        How("skip", "installs CUDA torch from the PyTorch wheel index, which CI cannot reach"),
    ("docs/gpu.md", "OUT=gpu-out bash deploy/gpu/protocol.sh"):
        How("skip", "needs an NVIDIA GPU (the script on a CPU with small sizes: "
                    "tests/e2e/test_gpu_protocol.py)"),
    ("docs/ros2.md", "agilegs serve --ros2 /bot1/agilegs --zenoh-connect tcp/robot:7447   # "
     "the server; robot: its address"):
        How("parse", "a server and the bridge on a robot, each running until stopped",
            stand_ins=("zenoh-bridge-ros2dds",)),
    ("docs/ros2.md", "from agilegs.client.ros2.robot import Ros2Robot"):
        How("skip", "lines of a robot's own code (its poses, images, depth); the whole robot, "
                    "deploy/ros2/play_robot.py, runs in tests/e2e/test_ros2.py"),
    ("docs/ros2.md", "from agilegs.client import Client"):
        How("skip", "reads the robot's own recording (capture.mcap); bags are written and read "
                    "in tests/client/test_ros2_bag.py"),
    ("docs/ros2.md", "agilegs bench service --pool 300"):
        How("parse", "a benchmark of minutes (its small run: tests/e2e/test_bench_service.py)"),
    ("docs/your-data.md", "# COLMAP: frames from the video, then structure from motion "
     "(sparse/0 and images/)"):
        How("skip", "needs a video and ffmpeg, COLMAP, instant-ngp and nerfstudio (what they "
                    "write is loaded in tests/data/test_captures.py and "
                    "tests/lab/bench/test_capture_scenes.py)"),
    ("docs/your-data.md", "agilegs bench run --scene lab/scenes/buddha --profile cpu "
     "--methods random,agile_plus --seeds 0 --out out/buddha"):
        How("parse", "minutes of CPU (the demo on this capture: "
                     "tests/e2e/test_demo_capture.py)"),
    ("docs/benchmarks.md", "S=lab/scenes"): BENCH,
    ("docs/benchmarks.md", "agilegs bench run --scene $S/plant --scene $S/boot --scene "
     "$S/koala --scene $S/floor \\"): BENCH,
    ("docs/benchmarks.md", "agilegs bench run $(for s in plant boot bob fish koala penguin floor "
     "skull spot stanford_bunny \\"): BENCH,
    ("docs/benchmarks.md", "agilegs bench value --scene $S/boot --scene $S/plant --scene "
     "$S/floor --horizon 100 \\"): BENCH,
    ("docs/benchmarks.md", "agilegs bench latency --scene $S/plant/plant.splat --pool 200 "
     "--width 128 --height 128 \\"): BENCH,
    ("docs/benchmarks.md", "for s in boot bob fish koala penguin skull spot stanford_bunny "
     "teapot violin; do"): BENCH,
    ("docs/benchmarks.md", "for c in skull_photos tankard flowerpot caliterra; do"): BENCH,
    ("docs/benchmarks.md", "agilegs bench run --profile cpu --seeds 0,1 --threads 1 --out "
     "runs/cpu-spread \\"): BENCH,
    ("docs/benchmarks.md", "agilegs bench run $(for s in skull_photos tankard flowerpot "
     "caliterra; do echo --scene $S/$s; \\"): BENCH,
    ("docs/benchmarks.md", "agilegs bench run --profile cpu_long --seeds 0,1 --threads 1 --out "
     "runs/objective-long \\"): BENCH,
    ("docs/benchmarks.md", "agilegs bench run --profile capture --seeds 0,1 --threads 1 --out "
     "runs/capture-spread \\"): BENCH,
    ("docs/benchmarks.md", "agilegs bench latency --scene $S/plant/plant.splat --max-gaussians "
     "1000000 --width 512 \\"): BENCH,
    ("docs/benchmarks.md", "agilegs bench render --scene $S/plant/plant.splat --sizes 128,256 "
     "--gaussians 20000,100000 \\"): BENCH,
    ("docs/benchmarks.md", "agilegs bench firstcall --fresh-cache     # an empty numba cache: "
     "a fresh machine"):
        How("parse", "minutes of compiling on a fresh cache (the command runs in "
                     "tests/e2e/test_bench_firstcall.py)"),
    ("docs/benchmarks.md", "agilegs bench service --pool 300"):
        How("parse", "a benchmark of minutes (its small run: tests/e2e/test_bench_service.py)"),
    ("docs/benchmarks.md", "OMP_NUM_THREADS=1 agilegs bench service --phases neighbour"):
        How("parse", "a benchmark of minutes (its small run: tests/e2e/test_bench_service.py)"),
    ("docs/benchmarks.md", "OMP_NUM_THREADS=1 agilegs bench service --phases deadline --scene "
     "$S/plant/plant.splat \\"):
        How("parse", "a benchmark of minutes (its small run: tests/e2e/test_bench_service.py)",
            env=(("S", "lab/scenes"),)),
    ("docs/benchmarks.md", "OMP_NUM_THREADS=1 agilegs bench bigmap --json bigmap.json     "
     "# default limits"):
        How("parse", "a million-Gaussian server session, minutes and GiBs (its small run: "
                     "tests/e2e/test_bench_bigmap.py)"),
    ("docs/benchmarks.md", "OMP_NUM_THREADS=1 agilegs bench bigmap --methods "
     "full_eig,fisherrf,cover \\"):
        How("parse", "twenty minutes of a million-Gaussian session (its small run: "
                     "tests/e2e/test_bench_bigmap.py)"),
    ("docs/benchmarks.md", "OMP_NUM_THREADS=1 agilegs bench edge --json edge.json"):
        How("parse", "1,000 connections and 64 bodies of 60 MiB, two minutes (its small run: "
                     "tests/e2e/test_bench_edge.py; its full run in the heavy lane)"),
    ("docs/benchmarks.md", "agilegs serve --no-zenoh --port 8000 --state-dir /tmp/fuzz-state   "
     "# with the limits below"):
        How("parse", "a server in one terminal and a fuzzing run of minutes in another (the "
                     "same run, smaller: tests/e2e/test_schemathesis.py)",
            stand_ins=("schemathesis",)),
}


def blocks() -> list[Block]:
    out = []
    for page in PAGES:
        text = (ROOT / page).read_text(encoding="utf-8")
        for m in re.finditer(r"^```(\w*)\n(.*?)^```", text, re.S | re.M):
            out.append(Block(page, text[:m.start()].count("\n") + 1, m.group(1), m.group(2)))
    return out


BLOCKS = blocks()
CODE_BLOCKS = [b for b in BLOCKS if b.lang in CODE]


def test_every_block_is_code_or_data_and_every_exception_is_a_block() -> None:
    assert {b.lang for b in BLOCKS} <= {*CODE, "text", "json", "toml"}, [
        (str(b), b.lang) for b in BLOCKS if b.lang not in (*CODE, "text", "json", "toml")]
    keys = [b.key for b in CODE_BLOCKS]
    assert len(keys) == len(set(keys)), "two code blocks start with the same line"
    assert set(HOW) <= set(keys), sorted(set(HOW) - set(keys))


LINKED = [*PAGES, *sorted(str(p.relative_to(ROOT)) for p in (ROOT / "notebook").rglob("*.md")),
          *sorted(str(p.relative_to(ROOT)) for p in (ROOT / "lab" / "scenes").rglob("*.md"))]


def heading_anchors(text: str) -> set[str]:
    """The anchors of a page's headings, as GitHub makes them (code blocks left out)."""
    text = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    return {re.sub(r"[^\w\- ]", "", m.group(1).strip().lower()).replace(" ", "-")
            for m in re.finditer(r"^#+ (.+)$", text, re.M)}


def test_heading_anchors_are_githubs() -> None:
    assert heading_anchors("# The paper's shape (`cpu_long`)\n## Embodied (K = 5)\n"
                           "```bash\n# a comment\n```\n") == {"the-papers-shape-cpu_long",
                                                            "embodied-k--5"}


@pytest.mark.parametrize("page", LINKED)
def test_every_relative_link_resolves(page: str) -> None:
    here = ROOT / page
    text = here.read_text(encoding="utf-8")
    broken = []
    for m in re.finditer(r"\]\(([^)\s]+)\)", text):
        url = m.group(1)
        if re.match(r"[a-z][a-z0-9+.-]*:", url):  # http:, https:, mailto:
            continue
        path, _, anchor = url.partition("#")
        target = (here.parent / path).resolve() if path else here
        if not target.exists():
            broken.append(url)
        elif anchor and target.suffix == ".md" and anchor not in heading_anchors(
                target.read_text(encoding="utf-8")):
            broken.append(url)
    assert not broken, f"{page}: links that lead nowhere: {broken}"


def _how(block: Block) -> How:
    return HOW.get(block.key, How("run"))


# ----------------------------------------------------------------------------- substitution
@dataclass
class Place:
    port: int
    zenoh: str
    page_port: int
    state: Path
    cwd: Path

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"


def substitute(text: str, place: Place) -> str:
    """The block with this machine's free ports and temporary folder."""
    return (text.replace("127.0.0.1:8000", f"127.0.0.1:{place.port}")
            .replace("--port 8000", f"--port {place.port}")
            .replace("tcp/127.0.0.1:7447", place.zenoh)
            .replace("port=8080", f"port={place.page_port}")
            .replace("./agilegs-state", str(place.state)))


def _env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("AGILEGS_")}
    env["AGILEGS_TORCH_THREADS"] = "1"  # the machine is shared with the test runner
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    return env


def _run(cmd: list[str], cwd: Path, timeout: float, env: dict[str, str] | None = None
         ) -> subprocess.CompletedProcess[str]:
    return subprocess.run(cmd, cwd=cwd, env=env or _env(), capture_output=True, text=True,
                          timeout=timeout)


def _place(tmp: Path) -> Place:
    return Place(free_port(), f"tcp/127.0.0.1:{free_port()}", free_port(),
                 tmp / "agilegs-state", tmp)


@pytest.fixture(scope="module")
def readme_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Place]:
    """The README's ``agilegs serve`` command, running (Zenoh on a free endpoint)."""
    place = _place(tmp_path_factory.mktemp("readme"))
    block = next(b for b in CODE_BLOCKS if _how(b).mode == "server" and b.lang == "bash"
                 and b.text.startswith("agilegs serve"))
    argv = shlex.split(substitute(block.text, place), comments=True)
    assert argv[:2] == ["agilegs", "serve"], argv
    cmd = [sys.executable, "-m", "agilegs.service.cli", *argv[1:],
           "--zenoh-listen", place.zenoh]
    log = open(place.cwd / "serve.log", "wb")  # noqa: SIM115 (closed below)
    proc = subprocess.Popen(cmd, cwd=place.cwd, env=_env(), stdout=log, stderr=subprocess.STDOUT)
    try:
        import httpx

        wait_until(lambda: httpx.get(f"{place.url}/healthz", timeout=1).status_code == 200,
                   90, alive=lambda: proc.poll() is None, what="the README's server")
        yield place
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)
        log.close()


# ----------------------------------------------------------------------------- the checks
def _json_documents(text: str) -> list[object]:
    dec, docs, i = json.JSONDecoder(), [], 0
    while i < len(text):
        if text[i].isspace():
            i += 1
            continue
        doc, i = dec.raw_decode(text, i)
        docs.append(doc)
    return docs


def _check_run(block: Block, place: Place, timeout: float = 240) -> str:
    code = substitute(block.text, place)
    if block.lang == "python":
        done = _run([sys.executable, "-c", code], ROOT, timeout)
    else:
        done = _run(["bash", "-e", "-o", "pipefail", "-c", code], place.cwd, timeout)
    assert done.returncode == 0, f"{block}:\n{code}\n{done.stdout[-3000:]}{done.stderr[-3000:]}"
    return done.stdout


@pytest.mark.timeout(400)
@pytest.mark.parametrize("block", [b for b in CODE_BLOCKS if _how(b).mode == "server"
                                   and not b.text.startswith("agilegs serve")], ids=str)
def test_the_block_runs_against_the_readme_server(block: Block, readme_server: Place) -> None:
    out = _check_run(block, readme_server, timeout=360)
    if "curl" in block.text:  # every answer is a body, none an error; the last a decision
        docs = _json_documents(out)
        assert docs and not [d for d in docs if isinstance(d, dict) and "error" in d], out
        assert isinstance(docs[-1], dict) and "chosen" in docs[-1], out
        lines = out.strip().splitlines()  # one body a line
        assert len(lines) == len(docs) == 3 and all(json.loads(x) for x in lines), out
        again = _json_documents(_check_run(block, readme_server, timeout=360))  # runs again
        assert not [d for d in again if isinstance(d, dict) and "error" in d], again
    if "asdict(robot.intrinsics)" in block.text:  # the README's loop: its four selections
        assert len(re.findall(r"^view \d+: \d+ ms$", out, re.M)) == 4, out
        again = _check_run(block, readme_server, timeout=360)  # and it runs again
        assert len(re.findall(r"^view \d+: \d+ ms$", again, re.M)) == 4, again
    if "read_bytes()" in block.text:  # the robot of files: four selections, twice, no torch
        no_torch = dataclasses.replace(block, text=block.text + "\nimport sys\n"
                                       "assert 'torch' not in sys.modules, 'torch imported'\n")
        for _ in range(2):
            out = _check_run(no_torch, readme_server, timeout=360)
            assert len(re.findall(r"^view \d+: \d+ ms$", out, re.M)) == 4, out


@pytest.mark.timeout(300)
@pytest.mark.parametrize("block", [b for b in CODE_BLOCKS if _how(b).mode == "run"], ids=str)
def test_the_block_runs(block: Block, tmp_path: Path) -> None:
    _check_run(block, _place(tmp_path))


@pytest.mark.timeout(300)
@pytest.mark.parametrize("block", [b for b in CODE_BLOCKS if _how(b).mode == "state"], ids=str)
def test_the_block_runs_on_a_state_folder(block: Block, tmp_path: Path) -> None:
    from inprocess import serve_in_process

    place = _place(tmp_path)
    with serve_in_process(place.state) as srv, srv.client() as c:
        c.create_session(SMALL_INTRINSICS, id="scene", bounds={"min": [-1.0] * 3,
                                                                "max": [1.0] * 3},
                         init_gaussians=50, pool=ring_poses(4))
    out = _check_run(block, place)
    assert "scene" in out and "damaged" in out, out


STAND_IN = textwrap.dedent("""\
    #!{python}
    import json, sys
    from pathlib import Path
    with open({log!r}, "a") as f:
        f.write(json.dumps([Path(sys.argv[0]).name, *sys.argv[1:]]) + "\\n")
    if Path(sys.argv[0]).name == "agilegs":
        from agilegs.service.cli import build_parser
        argv = sys.argv[1:]
        args = build_parser(argv).parse_args(argv)
        bench = args._module.startswith("agilegs.lab.bench.")
        scenes = (getattr(args, "scene", None) or []) if bench else []
        for scene in [scenes] if isinstance(scenes, str) else scenes:
            if not Path(scene).exists():
                sys.exit(f"--scene {{scene}}: not found")
    """)


@pytest.mark.parametrize("block", [b for b in CODE_BLOCKS if _how(b).mode == "parse"], ids=str)
def test_the_commands_parse(block: Block, tmp_path: Path) -> None:
    how = _how(block)
    place = _place(tmp_path)
    bin_dir, log = tmp_path / "bin", tmp_path / "calls.jsonl"
    bin_dir.mkdir()
    for name in ("agilegs", *how.stand_ins):
        exe = bin_dir / name
        exe.write_text(STAND_IN.format(python=sys.executable, log=str(log)))
        exe.chmod(exe.stat().st_mode | stat.S_IXUSR)
    env = {**_env(), **dict(how.env)}
    env["PATH"] = f"{bin_dir}{os.pathsep}{env['PATH']}"
    done = _run(["bash", "-e", "-o", "pipefail", "-c", substitute(block.text, place)], ROOT, 120,
                env=env)
    assert done.returncode == 0, f"{block}:\n{block.text}\n{done.stdout}{done.stderr}"
    calls = [json.loads(x) for x in log.read_text().splitlines()]
    assert [c for c in calls if c[0] == "agilegs"], calls  # the block ran its commands


@pytest.mark.parametrize("block", [b for b in CODE_BLOCKS if _how(b).mode == "ci"], ids=str)
def test_the_set_up_is_the_one_ci_runs(block: Block) -> None:
    ci = (ROOT / ".ci" / "run").read_text()
    line = next(x for x in ci.splitlines() if x.startswith("python3 -m venv"))
    setup, _, command = block.text.strip().rpartition(" && ")
    assert line.startswith(setup + " && "), (block.text, line)
    if command.startswith("agilegs"):
        from agilegs.service.cli import build_parser

        argv = shlex.split(command)[1:]
        build_parser(argv).parse_args(argv)
    else:
        assert block.text.strip() == line


def test_the_long_fuzzing_config_is_the_heavy_lanes() -> None:
    """docs/benchmarks.md's schemathesis.toml is the one the heavy lane writes."""
    sys.path.insert(0, str(Path(__file__).parent))
    from conftest import FULL, stateful_toml

    toml = next(b for b in BLOCKS if b.page == "docs/benchmarks.md" and b.lang == "toml")
    assert toml.text == stateful_toml(FULL)


@pytest.mark.parametrize("block", [b for b in CODE_BLOCKS if _how(b).mode == "skip"], ids=str)
def test_what_is_not_run_says_why(block: Block) -> None:
    assert len(_how(block).why) > 20
