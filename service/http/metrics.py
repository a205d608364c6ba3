"""Prometheus metrics of the API process: requests by route template (not raw path, so ids do
not explode the label set), upload volume, and job counts read from the metadata store at
scrape time (workers may live elsewhere; the store is the one place that knows every job).

Every label takes a bounded set of values, since anyone may call the API and /metrics answers
without a key: the route is a template or "unmatched", the status a number the server chose, and
the method one of HTTP's own or "other" (a client may send any token as a method, and each
made-up one would add series to the page)."""

from __future__ import annotations

import time
from collections.abc import Awaitable, Callable, Iterator

from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import GaugeMetricFamily, Metric
from prometheus_client.registry import Collector
from sqlalchemy import func, select
from starlette.requests import Request
from starlette.responses import Response

from geomatch_core.models import JOB_STATES, Job
from geomatch_core.store import MetadataStore

# RFC 9110's methods and PATCH (RFC 5789): what a client of this API, or a browser, sends
METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "DELETE", "CONNECT", "OPTIONS", "TRACE", "PATCH"})


def method_label(method: str) -> str:
    return method if method in METHODS else "other"


class JobsCollector(Collector):
    def __init__(self, store: MetadataStore) -> None:
        self.store = store

    def collect(self) -> Iterator[Metric]:
        g = GaugeMetricFamily("geomatch_jobs", "Jobs by kind and state", labels=["kind", "state"])
        counts = {(k, s): 0 for k in ("match", "reconstruct") for s in JOB_STATES}
        try:
            with self.store.session() as s:
                for kind, state, n in s.execute(
                    select(Job.kind, Job.state, func.count()).group_by(Job.kind, Job.state)
                ):
                    counts[(kind, state)] = int(n)
        except Exception:  # a scrape must not fail because the store hiccups; /readyz reports it
            return
        for (kind, state), n in sorted(counts.items()):
            g.add_metric([kind, state], n)
        yield g


class Metrics:
    def __init__(self, store: MetadataStore) -> None:
        self.registry = CollectorRegistry()
        self.requests = Counter(
            "geomatch_http_requests", "HTTP requests", ["method", "route", "status"], registry=self.registry
        )
        self.latency = Histogram(
            "geomatch_http_request_duration_seconds",
            "HTTP request latency",
            ["method", "route"],
            registry=self.registry,
            buckets=(0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30),
        )
        self.uploaded_bytes = Counter(
            "geomatch_uploaded_bytes", "Accepted image bytes", registry=self.registry
        )
        self.uploaded_images = Counter(
            "geomatch_uploaded_images", "Accepted new images", registry=self.registry
        )
        self.registry.register(JobsCollector(store))

    async def middleware(
        self, request: Request, call_next: Callable[[Request], Awaitable[Response]]
    ) -> Response:
        t0 = time.perf_counter()
        status = 500
        try:
            response = await call_next(request)
            status = response.status_code
            return response
        finally:
            route = request.scope.get("route")
            path = getattr(route, "path", "unmatched")
            method = method_label(request.method)
            self.requests.labels(method, path, str(status)).inc()
            self.latency.labels(method, path).observe(time.perf_counter() - t0)
