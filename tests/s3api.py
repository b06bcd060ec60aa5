"""A real S3 API on loopback for the tests: moto's server (``moto_server``, the server mode
that boto3 and s3fs test against) in a subprocess on 127.0.0.1 and a free port, with a bucket
made, and the ``AWS_*`` variables a client of it needs."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

from agilegs.lab.bench.fleet import s3_server

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
    """moto's S3 server on 127.0.0.1 (stopped on exit) with ``bucket`` made: the benchmark's
    own (:func:`agilegs.lab.bench.fleet.s3_server`)."""
    with s3_server(bucket) as endpoint:
        yield S3Api(endpoint, bucket)
