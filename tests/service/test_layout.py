"""The house rules, read from the code: no import cycles (function-level imports included),
the maths has no transport in it, the transports have no maths, the wire contract and the
client need no torch, and files stay small."""

from __future__ import annotations

import ast
from pathlib import Path

from conftest import ROOT

PACKAGES = {"schemas": "agilegs.schemas", "client": "agilegs.client", "service": "agilegs.service"}


def _modules() -> dict[str, Path]:
    out = {}
    for folder, pkg in PACKAGES.items():
        for path in (ROOT / folder).rglob("*.py"):
            rel = path.relative_to(ROOT / folder).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            out[".".join([pkg, *parts])] = path
    return out


MODULES = _modules()


def _imports(name: str, path: Path) -> set[str]:
    """Every agilegs module ``name`` imports, at any depth of its code (TYPE_CHECKING blocks
    left out: they import nothing at run time)."""
    tree = ast.parse(path.read_text())
    is_pkg = path.name == "__init__.py"
    base = name.split(".") if is_pkg else name.split(".")[:-1]
    found: set[str] = set()

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                mod = ".".join(base[: len(base) - node.level + 1] + ([node.module] if node.module
                                                                      else []))
            else:
                mod = node.module or ""
            for a in node.names:  # ``from pkg import submodule`` imports the submodule
                sub = f"{mod}.{a.name}"
                found.add(sub if sub in MODULES else mod)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return {m for m in found if m in MODULES and m != name}


GRAPH = {name: _imports(name, path) for name, path in MODULES.items()}


def test_no_import_cycles() -> None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def dfs(n: str) -> None:
        state[n] = 1
        stack.append(n)
        for d in sorted(GRAPH[n]):
            if state.get(d) == 1:
                cycle = stack[stack.index(d):] + [d]
                raise AssertionError("import cycle: " + " -> ".join(cycle))
            if d not in state:
                dfs(d)
        stack.pop()
        state[n] = 2

    for n in sorted(GRAPH):
        if n not in state:
            dfs(n)


def _third_party(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            out.add(node.module.split(".")[0])
    return out


def test_the_maths_has_no_transport_and_the_transports_no_maths() -> None:
    transports = {"fastapi", "starlette", "uvicorn", "zenoh", "httpx", "msgpack"}
    for name, path in MODULES.items():
        if name.startswith("agilegs.service.nbv"):
            assert not _third_party(path) & transports, name
            assert not {d for d in GRAPH[name]
                        if d.startswith("agilegs.service.") and not d.startswith(
                            "agilegs.service.nbv")}, name
    for name in ("agilegs.service.gateway", "agilegs.service.http_app",
                 "agilegs.service.http_routes", "agilegs.service.http_openapi",
                 "agilegs.service.zenoh_adapter", "agilegs.service.cluster"):
        assert "torch" not in _third_party(MODULES[name]), name
        assert not {d for d in GRAPH[name] if d.startswith("agilegs.service.nbv")}, name


def test_the_contract_and_the_client_need_no_torch() -> None:
    for name, path in MODULES.items():
        if name.startswith(("agilegs.schemas", "agilegs.client")):
            assert not _third_party(path) & {"torch", "fastapi", "uvicorn"}, name
            assert not {d for d in GRAPH[name] if d.startswith("agilegs.service")}, name


def test_files_stay_small() -> None:
    # one concept each that needs the length: the incremental 3DGS trainer and the rasterizer
    allowed = {"agilegs.service.mapper.mapper", "agilegs.service.nbv.rasterize"}
    for name, path in MODULES.items():
        if name.startswith("agilegs.service") and name not in allowed:
            n = len(path.read_text().splitlines())
            assert n <= 580, f"{name}: {n} lines"


def test_the_viewer_is_a_client_of_the_service() -> None:
    # it reaches the server through the client SDK only: no torch, no server code
    viewer = [n for n in MODULES if n.startswith("agilegs.service.viewer")]
    assert len(viewer) >= 6
    for name in viewer:
        assert not _third_party(MODULES[name]) & {"torch", "fastapi", "uvicorn"}, name
        inside = {d for d in GRAPH[name] if d.startswith("agilegs.service")}
        assert all(d.startswith("agilegs.service.viewer") for d in inside), (name, inside)
