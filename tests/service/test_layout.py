"""The house rules, read from the code: no import cycles (function-level and type-only imports
included, between modules and between folders), the maths has no transport, store, sessions
or wire in it, the transports have no maths, the wire contract and the client need no torch
and no server, the settings depend on nothing of ours, and files stay small."""

from __future__ import annotations

import ast
from pathlib import Path

from conftest import ROOT

PACKAGES = {"config": "agilegs.config", "schemas": "agilegs.schemas", "client": "agilegs.client",
            "service": "agilegs.service", "lab": "agilegs.lab"}


def _modules() -> dict[str, Path]:
    out = {}
    for folder, pkg in PACKAGES.items():
        for path in (ROOT / folder).rglob("*.py"):
            rel = path.relative_to(ROOT / folder).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            out[".".join([pkg, *parts])] = path
    return out


MODULES = _modules()


def _imports(name: str, path: Path, type_only: bool = False) -> set[str]:
    """Every agilegs module ``name`` imports, at any depth of its code (TYPE_CHECKING blocks
    left out, as they import nothing at run time, unless ``type_only``)."""
    tree = ast.parse(path.read_text())
    is_pkg = path.name == "__init__.py"
    base = name.split(".") if is_pkg else name.split(".")[:-1]
    found: set[str] = set()

    def visit(node: ast.AST) -> None:
        if (not type_only and isinstance(node, ast.If)
                and "TYPE_CHECKING" in ast.unparse(node.test)):
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
TYPED_GRAPH = {name: _imports(name, path, type_only=True) for name, path in MODULES.items()}


def _check_acyclic(graph: dict[str, set[str]]) -> None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def dfs(n: str) -> None:
        state[n] = 1
        stack.append(n)
        for d in sorted(graph.get(n, ())):
            if state.get(d) == 1:
                cycle = stack[stack.index(d):] + [d]
                raise AssertionError("import cycle: " + " -> ".join(cycle))
            if d not in state:
                dfs(d)
        stack.pop()
        state[n] = 2

    for n in sorted(graph):
        if n not in state:
            dfs(n)


def test_no_import_cycles() -> None:
    _check_acyclic(GRAPH)


def test_no_import_cycles_type_only_imports_included() -> None:
    _check_acyclic(TYPED_GRAPH)


def _folder(name: str) -> str:
    """The node of ``name`` in the folder graph: a subpackage of the service (sessions, nbv
    with its own subfolders, mapper, bench, ...) as one node, a top-level module of the
    service as itself, every other package (schemas, client, config) as one node."""
    parts = name.split(".")
    if parts[1] != "service":
        return ".".join(parts[:2])
    sub = ".".join(parts[:3])
    return sub if sub in MODULES and MODULES[sub].name == "__init__.py" else name


def test_no_folder_cycles() -> None:
    folders: dict[str, set[str]] = {}
    for name, deps in TYPED_GRAPH.items():
        node = _folder(name)
        folders.setdefault(node, set()).update(
            _folder(d) for d in deps if _folder(d) != node)
    _check_acyclic(folders)


def _reaches(name: str, prefixes: tuple[str, ...]) -> set[str]:
    return {d for d in TYPED_GRAPH[name] if d.startswith(prefixes)}


LAYERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("settings and errors", ("settings", "errors")),
    ("maths", ("nbv", "mapper", "data")),
    ("store", ("store",)),
    ("sessions", ("sessions",)),
    ("transports", ("transports",)),
    ("server", ("server",)),
    ("commands", ("serve", "cli", "launch", "store_tool", "export", "viewer")),
)
"""The service's layers, bottom up: the folders (or top-level modules) of ``service/`` in each.
A module imports from its own layer and the layers below only."""


def _layer(name: str) -> int:
    """The layer (index in :data:`LAYERS`) of the service's module ``name``."""
    room = name.split(".")[2]
    found = [i for i, (_, rooms) in enumerate(LAYERS) if room in rooms]
    assert len(found) == 1, f"{name}: service/{room} is in {len(found)} layers of LAYERS"
    return found[0]


def test_every_folder_of_the_service_has_one_layer() -> None:
    rooms = {p.stem for p in (ROOT / "service").iterdir()
             if p.suffix == ".py" and p.stem != "__init__" or (p / "__init__.py").exists()}
    listed = [room for _, layer in LAYERS for room in layer]
    assert sorted(listed) == sorted(rooms)


def test_each_layer_imports_only_from_itself_and_below() -> None:
    for name, deps in TYPED_GRAPH.items():
        if not name.startswith("agilegs.service."):
            continue
        above = {d for d in deps if d.startswith("agilegs.service.") and _layer(d) > _layer(name)}
        assert not above, (f"{name} ({LAYERS[_layer(name)][0]}) imports from a layer above: "
                           f"{sorted(above)}")


def test_the_server_imports_nothing_of_the_lab() -> None:
    """The lab measures and demonstrates the server: nothing of ``agilegs.service`` imports it
    (type-only imports included), and its commands reach the CLI through an entry point."""
    service = [n for n in MODULES if n.startswith("agilegs.service")]
    lab = [n for n in MODULES if n.startswith("agilegs.lab")]
    assert len(service) > 50 and len(lab) > 20
    for name in service:
        assert not _reaches(name, ("agilegs.lab",)), (name, _reaches(name, ("agilegs.lab",)))
    for name in ("agilegs.schemas", "agilegs.client", "agilegs.config"):
        assert not any(_reaches(n, ("agilegs.lab",)) for n in MODULES if n.startswith(name))
    text = (ROOT / "service" / "cli.py").read_text()
    assert "agilegs.lab" not in text


def test_no_forbidden_arrow() -> None:
    """maths -> wire (or anything of the service but the settings); wire -> service or
    client; client -> service; config -> anything of ours."""
    forbidden = {
        "agilegs.service.nbv": ("agilegs.schemas", "agilegs.client"),
        "agilegs.schemas": ("agilegs.service", "agilegs.client"),
        "agilegs.client": ("agilegs.service",),
        "agilegs.config": ("agilegs.service", "agilegs.schemas", "agilegs.client"),
    }
    seen = set()
    for name in MODULES:
        for src, bad in forbidden.items():
            if name == src or name.startswith(src + "."):
                seen.add(src)
                assert not _reaches(name, bad), (name, _reaches(name, bad))
    assert seen == set(forbidden)
    for name, path in MODULES.items():
        if name.startswith(("agilegs.client", "agilegs.config", "agilegs.schemas")):
            assert "torch" not in _third_party(path), name


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
                            ("agilegs.service.nbv", "agilegs.service.settings"))}, name
    transports = [n for n in MODULES if n.startswith("agilegs.service.transports")]
    assert len(transports) >= 15
    for name in transports:
        assert "torch" not in _third_party(MODULES[name]), name
        assert not {d for d in GRAPH[name] if d.startswith("agilegs.service.nbv")}, name


def test_the_settings_depend_on_nothing_of_ours_and_no_torch() -> None:
    """The settings are read by every part (the viewer too, which has no torch): they import
    nothing of ours (at any depth of their code, type-only imports included) and no torch;
    what needs the machine or the client is checked by ``agilegs serve``."""
    name = "agilegs.service.settings"
    assert not TYPED_GRAPH[name], sorted(TYPED_GRAPH[name])
    assert not _third_party(MODULES[name]) & {"torch", "numba", "agilegs"}, name


def test_the_contract_and_the_client_need_no_torch() -> None:
    for name, path in MODULES.items():
        if name.startswith(("agilegs.schemas", "agilegs.client")):
            assert not _third_party(path) & {"torch", "fastapi", "uvicorn"}, name
            assert not {d for d in GRAPH[name] if d.startswith("agilegs.service")}, name


def test_files_stay_small() -> None:
    # one concept each that needs the length: the incremental 3DGS trainer and the rasterizer
    allowed = {"agilegs.service.mapper.mapper", "agilegs.service.nbv.rasterize"}
    for name, path in MODULES.items():
        if name.startswith(("agilegs.service", "agilegs.lab")) and name not in allowed:
            n = len(path.read_text().splitlines())
            assert n <= 580, f"{name}: {n} lines"


def _long_functions(tree: ast.Module, limit: int) -> list[tuple[str, int, bool]]:
    """(name, lines, compiled) of each function of over ``limit`` lines; ``compiled``: a
    kernel (a decorator of the module's numba or Triton ``jit``)."""
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            n = node.end_lineno - node.lineno + 1 if node.end_lineno else 0
            if n > limit:
                compiled = any("jit" in ast.unparse(d) for d in node.decorator_list)
                out.append((node.name, n, compiled))
    return out


def test_no_function_is_longer_than_a_screenful_but_the_kernels_walks() -> None:
    """A function over 120 lines is a compiled kernel's walk (numba or Triton: the loops over
    tiles, pixels and samples that cannot call back into Python), in ``nbv/kernels``."""
    assert _long_functions(ast.parse("def f():\n" + "    x = 1\n" * 130), 120) == [
        ("f", 131, False)]
    bad = []
    for name, tree in TREES.items():
        for fn, n, compiled in _long_functions(tree, 120):
            if not (compiled and name.startswith("agilegs.service.nbv.kernels.")):
                bad.append(f"{name}.{fn}: {n} lines")
    assert not bad, bad


def test_the_viewer_is_a_client_of_the_service() -> None:
    # it reaches the server through the client SDK only: no torch, no server code (its
    # environment variable, the token, through the settings)
    viewer = [n for n in MODULES if n.startswith("agilegs.service.viewer")]
    assert len(viewer) >= 6
    for name in viewer:
        assert not _third_party(MODULES[name]) & {"torch", "fastapi", "uvicorn"}, name
        inside = {d for d in GRAPH[name] if d.startswith("agilegs.service")}
        assert all(d.startswith("agilegs.service.viewer") or d == "agilegs.service.settings"
                   for d in inside), (name, inside)


def _reads_environment(tree: ast.Module) -> bool:
    """Whether the code reads an environment variable (``os.environ.get``, ``os.getenv``,
    ``os.environ[...]``; copying the whole environment for a child process is no read)."""
    for node in ast.walk(tree):
        text = ast.unparse(node)
        if isinstance(node, ast.Attribute | ast.Name) and text in (
                "os.environ.get", "os.getenv", "environ.get", "getenv"):
            return True
        if isinstance(node, ast.Subscript) and text.startswith(("os.environ[", "environ[")):
            return True
    return False


def test_environment_variables_are_read_by_the_settings_only() -> None:
    assert _reads_environment(ast.parse("import os\nx = os.environ.get('A')\n"))
    assert _reads_environment(ast.parse("import os\nx = os.environ['A']\n"))
    assert _reads_environment(ast.parse("import os\nx = list(map(os.environ.get, 'AB'))\n"))
    assert not _reads_environment(ast.parse("import os\nx = dict(os.environ.items())\n"))
    readers = {name for name, tree in TREES.items() if _reads_environment(tree)}
    assert readers == {"agilegs.service.settings"}, readers


# The public faces: a package whose ``__init__`` gathers the names its users import (the wire
# contract, the client SDK and its ROS 2 part). Every other module defines what it exports.
FACES = ("agilegs.schemas", "agilegs.client", "agilegs.client.ros2", "agilegs.service.nbv")
TREES = {name: ast.parse(path.read_text()) for name, path in MODULES.items()}


def _only_imports(tree: ast.Module) -> bool:
    """Whether a module's body is imports alone (besides its docstring, ``__all__`` and
    ``if TYPE_CHECKING:`` blocks): it re-exports and defines nothing."""
    body = tree.body[1:] if tree.body and isinstance(tree.body[0], ast.Expr) else tree.body
    imports = 0
    for node in body:
        if isinstance(node, ast.ImportFrom | ast.Import):
            imports += not (isinstance(node, ast.ImportFrom) and node.module == "__future__")
        elif not (isinstance(node, ast.Assign) and ast.unparse(node.targets[0]) == "__all__"
                  or isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)):
            return False
    return imports > 0


def test_no_module_only_re_exports() -> None:
    assert _only_imports(ast.parse('"""x"""\nfrom .a import b\n__all__ = ["b"]\n'))
    assert not _only_imports(ast.parse('"""x"""\nfrom .a import b\nc = b\n'))
    assert not _only_imports(ast.parse('"""x"""\n'))
    bad = [name for name, tree in TREES.items() if name not in FACES and _only_imports(tree)]
    assert not bad, bad


def _absolute(node: ast.ImportFrom, name: str | None, path: Path) -> str:
    if not node.level or name is None:
        return node.module or ""
    base = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    return ".".join(base[: len(base) - node.level + 1] + ([node.module] if node.module else []))


def _top_level(tree: ast.Module) -> list[ast.stmt]:
    out: list[ast.stmt] = []
    for node in tree.body:
        out += node.body + node.orelse if isinstance(node, ast.If) else [node]
    return out


def _defines(module: str, name: str) -> bool:
    for node in _top_level(TREES[module]):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            if node.name == name:
                return True
        elif isinstance(node, ast.Assign | ast.AnnAssign):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            if any(isinstance(t, ast.Name) and t.id == name for t in targets):
                return True
    return False


def _origin(module: str, name: str) -> str:
    """The module that defines ``name``, followed from ``module`` through its imports."""
    for _ in range(20):
        if module not in TREES or _defines(module, name):
            return module
        for node in _top_level(TREES[module]):
            if isinstance(node, ast.ImportFrom) and any(
                    (a.asname or a.name) == name for a in node.names):
                src = _absolute(node, module, MODULES[module])
                alias = next(a for a in node.names if (a.asname or a.name) == name)
                if f"{src}.{alias.name}" in MODULES:
                    return f"{src}.{alias.name}"
                module, name = src, alias.name
                break
        else:
            return module
    return module


def _face_names(face: str) -> set[str]:
    for node in TREES[face].body:
        if isinstance(node, ast.Assign) and ast.unparse(node.targets[0]) == "__all__":
            return set(ast.literal_eval(node.value))
    return set()


def _import_path(importer: str, module: str, name: str) -> str:
    """The one path ``name`` is imported from: the face of its package when the face lists
    it (and the importer is outside the package), else the module that defines it."""
    origin = _origin(module, name)
    for face in sorted(FACES, key=len, reverse=True):
        inside = importer == face or importer.startswith(face + ".")
        if (origin.startswith(face + ".") and name in _face_names(face) and not inside
                and _origin(face, name) == origin):
            return face
    return origin


def test_one_import_path_per_name() -> None:
    """Every import of one of our names, in the package, the tests and the deploy files,
    names the one path of :func:`_import_path` (no import through a module that merely
    imported it)."""
    modules = {path.resolve(): name for name, path in MODULES.items()}
    files = [p for d in ("config", "schemas", "client", "service", "lab", "tests", "deploy")
             for p in (ROOT / d).rglob("*.py")]
    assert len(files) > len(MODULES)
    bad = []
    for path in files:
        importer = modules.get(path.resolve())
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.ImportFrom):
                continue
            module = _absolute(node, importer, path)
            if module not in TREES:
                continue
            for a in node.names:
                if f"{module}.{a.name}" not in MODULES:
                    want = _import_path(importer or "", module, a.name)
                    if want != module:
                        bad.append(f"{path.relative_to(ROOT)}:{node.lineno}: {a.name} from "
                                   f"{module}, not {want}")
    assert not bad, "\n".join(bad)


def test_the_import_path_rule_sees_a_second_path() -> None:
    assert _import_path("tests", "agilegs.schemas.geometry", "Pose") == "agilegs.schemas"
    assert _import_path("agilegs.schemas.views", "agilegs.schemas.geometry",
                        "Pose") == "agilegs.schemas.geometry"
    assert _import_path("tests", "agilegs.service.sessions.registry",
                        "Settings") == "agilegs.service.settings"
