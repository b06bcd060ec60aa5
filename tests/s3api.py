"""A real S3 API on loopback for the tests: moto's server (``moto_server``, the server mode
that boto3 and s3fs test against) in a subprocess on 127.0.0.1 and a free port, with a bucket
made, and the ``AWS_*`` variables a client of it needs."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import httpx

from agilegs.service.launch import free_port

__all__ = ["S3Api", "s3_api"]


@dataclass(frozen=True)
class S3Api:
    """A running S3 API: its endpoint, the bucket made, the environment its clients take."""

    endpoint: str
    bucket: str

    @property
    def env(self) -> dict[str, str]:
        return {"AWS_ACCESS_KEY_ID": "testing", "AWS_SECRET_ACCESS_KEY": "testing",
                "AWS_REGION": "us-east-1", "AWS_ENDPOINT_URL": self.endpoint}

    def url(self, prefix: str = "state") -> str:
        return f"s3://{self.bucket}/{prefix}"


@contextmanager
def s3_api(bucket: str = "agilegs-test") -> Iterator[S3Api]:
    """moto's S3 server on 127.0.0.1 (stopped on exit) with ``bucket`` made."""
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p",
                             str(port)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            env={**os.environ, "MOTO_PORT": str(port)})
    endpoint = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 30
        while True:
            try:
                # a bucket is made by PUT /<bucket> (moto does not check signatures)
                if httpx.put(f"{endpoint}/{bucket}", timeout=2).status_code in (200, 409):
                    break
            except httpx.HTTPError:
                pass
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("moto's S3 server did not start")
            time.sleep(0.1)
        yield S3Api(endpoint, bucket)
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
