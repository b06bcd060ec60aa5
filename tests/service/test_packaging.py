"""pyproject.toml builds without setuptools' warnings: the licence as an SPDX string, and every
folder whose files the wheel ships listed in ``packages`` (else setuptools warns, per folder,
that it "would be ignored")."""

from __future__ import annotations

import fnmatch
import tomllib
from pathlib import Path

from conftest import ROOT

PROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())


def test_the_licence_is_an_spdx_string_for_a_setuptools_that_reads_it() -> None:
    assert PROJECT["project"]["license"] == "Apache-2.0"
    assert "setuptools>=77" in PROJECT["build-system"]["requires"]


def _folder(package: str) -> Path:
    dirs = PROJECT["tool"]["setuptools"]["package-dir"]
    top = max((p for p in dirs if package == p or package.startswith(p + ".")), key=len)
    rest = package[len(top):].lstrip(".")
    return ROOT / dirs[top] / Path(*rest.split(".")) if rest else ROOT / dirs[top]


def test_every_folder_of_shipped_files_is_a_listed_package() -> None:
    tool = PROJECT["tool"]["setuptools"]
    packages = set(tool["packages"])
    missing = []
    for package, patterns in tool["package-data"].items():
        base = _folder(package)
        for pattern in patterns:
            for path in base.rglob("*"):
                rel = path.relative_to(base).as_posix()
                if not path.is_file() or not fnmatch.fnmatch(rel, pattern):
                    continue
                for parent in path.relative_to(base).parents:
                    if parent == Path("."):
                        continue
                    name = f"{package}.{'.'.join(parent.parts)}"
                    if all(p.isidentifier() for p in parent.parts) and name not in packages:
                        missing.append(name)
    assert not sorted(set(missing)), sorted(set(missing))
