"""docs/extending.md's "Where things are" table matches the tree: every path it names exists
and imports as it says, every folder and top-level module of ``service/`` has its row; and the
tests mirror the tree (``tests/<folder>/`` for ``service/<folder>/``)."""

from __future__ import annotations

import re
from pathlib import Path

from conftest import ROOT

PACKAGES = {"agilegs.config": "config", "agilegs.schemas": "schemas", "agilegs.client": "client",
            "agilegs.service": "service", "agilegs.lab": "lab"}


def table() -> list[tuple[str, str]]:
    """(folder, imports as) of each row of the table."""
    text = (ROOT / "docs" / "extending.md").read_text()
    section = text[text.index("## Where things are"):]
    rows = [line for line in section.splitlines()[2:] if line.startswith("| `")]
    out = []
    for row in rows:
        cells = [c.strip() for c in row.strip("|").split("|")]
        out.append((cells[0].strip("`"), cells[1].strip("`")))
    assert len(out) >= 10
    return out


def module_file(name: str) -> Path | None:
    """The file of the module ``name`` through the package-dir mapping of pyproject.toml."""
    for pkg, folder in PACKAGES.items():
        if name == pkg or name.startswith(pkg + "."):
            rest = name[len(pkg):].lstrip(".").split(".") if name != pkg else []
            base = ROOT / folder / Path(*rest) if rest else ROOT / folder
            for candidate in (base / "__init__.py", base.with_suffix(".py")):
                if candidate.is_file():
                    return candidate
    return None


def test_every_path_of_the_table_exists_and_imports_as_it_says() -> None:
    for folder, module in table():
        path = ROOT / folder
        assert path.exists(), f"docs/extending.md names {folder}, which does not exist"
        if module:
            found = module_file(module)
            assert found is not None, module
            assert found in (path, path / "__init__.py"), (folder, module, found)


def test_every_folder_and_module_of_the_service_has_its_row() -> None:
    named = {folder for folder, _ in table()}
    for path in sorted((ROOT / "service").iterdir()):
        if (path / "__init__.py").exists():
            assert f"service/{path.name}/" in named, f"docs/extending.md lacks service/{path.name}/"
        elif path.suffix == ".py" and path.name != "__init__.py":
            assert f"service/{path.name}" in named, f"docs/extending.md lacks service/{path.name}"
    for path in sorted((ROOT / "lab").iterdir()):
        if (path / "__init__.py").exists():
            assert f"lab/{path.name}/" in named, f"docs/extending.md lacks lab/{path.name}/"
        elif path.suffix == ".py" and path.name != "__init__.py":
            assert f"lab/{path.name}" in named, f"docs/extending.md lacks lab/{path.name}"
    for top in ("config/", "schemas/", "client/", "lab/", "deploy/", "tests/"):
        assert top in named


def test_the_table_test_sees_a_missing_row() -> None:
    assert module_file("agilegs.service.transports.gateway") == (
        ROOT / "service" / "transports" / "gateway.py")
    assert module_file("agilegs.service.no_such_module") is None


def test_the_tests_mirror_the_tree() -> None:
    """A folder of tests/ is a folder of service/ (or client, schemas, config, lab), or one of
    service (the top-level modules), docs, e2e; a folder inside one of them is a subfolder of
    what it tests (``tests/nbv/anchor/`` tests ``service/nbv/anchor/``)."""
    rooms = {p.name for p in (ROOT / "service").iterdir() if (p / "__init__.py").exists()}
    allowed = rooms | {"client", "schemas", "config", "lab", "service", "docs", "e2e"}
    folders = {p.name for p in (ROOT / "tests").iterdir()
               if p.is_dir() and not re.match(r"^(__pycache__|\.)", p.name)}
    assert folders <= allowed, folders - allowed
    for tests, package in [(ROOT / "tests" / "lab", ROOT / "lab")] + [
            (ROOT / "tests" / room, ROOT / "service" / room) for room in sorted(rooms)]:
        if not tests.is_dir():
            continue
        inside = {p.name for p in tests.iterdir()
                  if p.is_dir() and not re.match(r"^(__pycache__|\.)", p.name)}
        subfolders = {p.name for p in package.iterdir() if (p / "__init__.py").exists()}
        assert inside <= subfolders, (tests, inside - subfolders)
    assert {"anchor", "kernels", "methods"} <= {
        p.name for p in (ROOT / "tests" / "nbv").iterdir() if p.is_dir()}
    assert {"sessions", "store", "transports", "mapper", "data", "viewer", "nbv"} <= folders
