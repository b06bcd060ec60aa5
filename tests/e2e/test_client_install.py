"""The client SDK in a fresh interpreter: importing it loads neither torch nor the server."""

from __future__ import annotations

import subprocess
import sys


def test_import_does_not_load_torch() -> None:
    code = ("import sys, agilegs.client, agilegs.schemas; "
            "from agilegs.client import Client, AsyncClient, ZenohClient; "
            "bad = [m for m in ('torch', 'fastapi', 'uvicorn') if m in sys.modules]; "
            "print(bad); sys.exit(1 if bad else 0)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stdout + out.stderr
