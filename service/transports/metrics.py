"""Prometheus metrics of the server (served at ``/metrics``).

- ``agilegs_requests_total{transport, op, status}``: requests answered, by status.
- ``agilegs_errors_total{transport, op, code}``: refused or failed requests, by error code.
- ``agilegs_selection_seconds{method}``: selection core time (``latency_ms.total``).
- ``agilegs_selection_stage_seconds{method, stage}``: anchor, scoring, leverage, rerank.
- ``agilegs_selection_server_seconds{method}``: arrival to response (``server_ms``).
- ``agilegs_sessions``: sessions held; ``agilegs_sessions_damaged``: those of them damaged.
- ``agilegs_writes_refused_total{source, op}``: state changes refused because the state
  folder is full (source: ``http``, ``zenoh``, or ``mapper`` for a map publication).
"""

from __future__ import annotations

from collections.abc import Callable

from prometheus_client import (
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    generate_latest,
)

from agilegs.schemas import SelectResponse

__all__ = ["Metrics"]

_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0,
            60.0, 120.0)


class Metrics:
    """The server's collectors, in a registry of their own (one per app)."""

    def __init__(self, sessions: Callable[[], int] | None = None,
                 damaged: Callable[[], int] | None = None) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        self.requests = Counter(
            "agilegs_requests", "requests answered", ("transport", "op", "status"),
            registry=self.registry,
        )
        self.errors = Counter(
            "agilegs_errors", "requests refused or failed", ("transport", "op", "code"),
            registry=self.registry,
        )
        self.selection = Histogram(
            "agilegs_selection_seconds", "selection core time", ("method",),
            buckets=_BUCKETS, registry=self.registry,
        )
        self.stage = Histogram(
            "agilegs_selection_stage_seconds", "selection time per stage", ("method", "stage"),
            buckets=_BUCKETS, registry=self.registry,
        )
        self.server = Histogram(
            "agilegs_selection_server_seconds", "selection request, arrival to response",
            ("method",), buckets=_BUCKETS, registry=self.registry,
        )
        self.sessions = Gauge("agilegs_sessions", "sessions held", registry=self.registry)
        if sessions is not None:
            self.sessions.set_function(lambda: float(sessions()))
        self.damaged = Gauge("agilegs_sessions_damaged", "sessions held whose files do not "
                             "check out", registry=self.registry)
        if damaged is not None:
            self.damaged.set_function(lambda: float(damaged()))
        self.writes_refused = Counter(
            "agilegs_writes_refused", "state changes refused: the state folder is full",
            ("source", "op"), registry=self.registry,
        )

    def observe_request(self, transport: str, op: str, status: int, code: str | None = None
                        ) -> None:
        self.requests.labels(transport, op, str(status)).inc()
        if code is not None:
            self.errors.labels(transport, op, code).inc()

    def observe_refused_write(self, source: str, op: str) -> None:
        self.writes_refused.labels(source, op).inc()

    def observe_selection(self, resp: SelectResponse) -> None:
        lat = resp.latency_ms
        self.selection.labels(resp.method).observe(lat.get("total", 0.0) / 1e3)
        for stage, ms in lat.items():
            if stage != "total":
                self.stage.labels(resp.method, stage).observe(ms / 1e3)
        if resp.server_ms is not None:
            self.server.labels(resp.method).observe(resp.server_ms / 1e3)

    def render(self) -> bytes:
        return generate_latest(self.registry)
