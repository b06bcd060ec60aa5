"""docs/server.md lists exactly what the server serves: every operation with its HTTP route and
Zenoh key, every error code with its status, every setting with its environment variable and
default. The rows are generated here from the code and must appear in the page as written
(``python tests/docs/test_docs.py`` prints them)."""

from __future__ import annotations

from pathlib import Path

from agilegs.schemas import OPERATIONS
from agilegs.schemas.errors import ERROR_STATUS, ErrorCode
from agilegs.service.settings import Settings

ROOT = Path(__file__).resolve().parents[2]


def operation_rows() -> list[str]:
    rows = []
    for op in OPERATIONS.values():
        key = (f"`agilegs/@service/{op.name}`" if op.scope == "service"
               else f"`agilegs/<session>/{op.name}`")
        req = op.request.__name__ if op.request is not None else "–"
        rows.append(f"| `{op.name}` | `{op.http_method} {op.http_path}` | {key} | {req} | "
                    f"{op.response.__name__} | {op.summary} |")
    return rows


def error_rows() -> list[str]:
    return [f"| `{code.value}` | {ERROR_STATUS[code]} |" for code in ErrorCode]


def setting_rows() -> list[str]:
    rows = []
    for name, field in Settings.model_fields.items():
        default = field.get_default(call_default_factory=True)
        if name == "token":
            default = "(none)"
        elif isinstance(default, list):
            default = ",".join(default) or "(none)"
        rows.append(f"| `AGILEGS_{name.upper()}` | `{default}` | {field.description} |")
    return rows


def test_server_page_lists_every_operation_error_and_setting() -> None:
    text = (ROOT / "docs" / "server.md").read_text()
    for row in operation_rows() + error_rows() + setting_rows():
        assert row in text, f"docs/server.md lacks the row:\n{row}"
    # and no row of an operation, code or setting that no longer exists
    listed = {line.split("|")[1].strip() for line in text.splitlines()
              if line.startswith("| `") and not line.startswith("| `agilegs/")}
    known = ({f"`{op}`" for op in OPERATIONS} | {f"`{c.value}`" for c in ErrorCode}
             | {f"`AGILEGS_{n.upper()}`" for n in Settings.model_fields})
    assert listed <= known, listed - known


if __name__ == "__main__":
    print("\n".join(operation_rows()), "\n")
    print("\n".join(error_rows()), "\n")
    print("\n".join(setting_rows()))
