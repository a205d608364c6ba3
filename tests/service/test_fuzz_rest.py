"""Property-based fuzzing of the REST API from its own OpenAPI schema: no request, however odd, may
get a server error or an answer the schema does not describe.

schemathesis runs as one would run it from a shell (``st run``, every phase: the schema's examples,
coverage of boundaries and of what the schema forbids, random fuzzing, and stateful sequences over
the links it infers) against a real ``geomatch serve`` on loopback, authenticated with a key, with
every check on (``--checks all``: not_a_server_error, status_code_conformance,
content_type_conformance, response_headers_conformance, response_schema_conformance,
positive_data_acceptance, negative_data_rejection, missing_required_header, unsupported_method,
allow_header_conformance, use_after_free, ensure_resource_availability, ignored_auth, ...) and
max_response_time 10 s. The HAR report it writes counts the requests: at least 1000, every
operation among them.

Redis mode with no worker, over SQLite and over PostgreSQL: a job the fuzzer manages to start stays
queued, so no network ever runs here (it cannot start one anyway: no generated file is an image),
and a matches picture waits 3 s for a worker instead of 120.

Three checks are tuned, for reasons no schema can carry (see ``CONFIG``):

- positive_data_acceptance: an upload's parts are binary strings to the schema, but only an image
  of an accepted format is one (400, 413, 415 otherwise), whether a match job can start depends
  on the project's images (at least two; explicit pairs must name them): 422 otherwise, and a GCP
  file is any text to the schema but one the project's images can use only when it names them;
- ensure_resource_availability, for the project's COLMAP database, its model and survey report,
  match pictures and GCP file: those are made by jobs or by a PUT of their own, not by creating
  the project, and until then 404 is the documented answer (the stateful phase links them to
  POST /v1/projects and would call the 404 a lost resource);
- not_a_server_error on /readyz: with no worker its 503 is the answer a load balancer needs.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from urllib.parse import urlsplit

import httpx
import pytest

from .harness import Deployment, metadata_database, serving

pytestmark = pytest.mark.service

SEED = int(os.environ.get("GEOMATCH_FUZZ_SEED", "1"))  # another seed explores other inputs
MAX_EXAMPLES = 50  # per operation and phase: over MIN_REQUESTS requests, about a minute a store on two cores
MIN_REQUESTS = 1000
ST = [sys.executable, "-m", "schemathesis.cli"]

CONFIG = """
seed = {seed}
workers = 1
request-timeout = 30
headers = {{ Authorization = "Bearer {key}" }}

[checks]
enabled = true
max_response_time = 10.0

[generation]
mode = "all"
max-examples = {max_examples}

[[operations]]
include-name = "POST /v1/projects/{{project_id}}/images"
checks.positive_data_acceptance.expected-statuses = ["2xx", "401", "404", "409", "400", "413", "415"]

[[operations]]
include-name = "POST /v1/projects/{{project_id}}/match"
checks.positive_data_acceptance.expected-statuses = ["2xx", "401", "404", "409", "422"]

[[operations]]
include-name = "PUT /v1/projects/{{project_id}}/gcp"
checks.positive_data_acceptance.expected-statuses = ["2xx", "401", "404", "400", "413", "415", "422"]

[[operations]]
include-name = "GET /readyz"
checks.not_a_server_error.enabled = false

[[operations]]
include-path-regex = "^/v1/projects/\\\\{{project_id\\\\}}/(database|model|report|pairs/|gcp)"
checks.ensure_resource_availability.enabled = false
"""


@pytest.fixture(scope="module", params=["sqlite", "postgresql"])
def api(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory, redis_url: str
) -> Iterator[tuple[Deployment, str]]:
    """The server over each metadata store: PostgreSQL refuses some text SQLite keeps (NUL)."""
    with metadata_database(request.param) as url:
        env = {"DATABASE_URL": url} if url else {}
        root = tmp_path_factory.mktemp(f"fuzz-rest-{request.param}")
        # no rate limit: the fuzzer sends ~90 requests a second, and whether a request meets the
        # tenant's 429 would then depend on the machine's speed, not on the request; the limit has
        # its own tests (test_limits.py)
        d = Deployment(root, redis_url, GEOMATCH_RENDER_TIMEOUT="3", GEOMATCH_RATE_LIMIT="0", **env)
        try:
            d.start_server()
            yield d, d.create_key("fuzz")
        finally:
            d.stop()


def operations(schema: dict) -> list[tuple[str, str, re.Pattern[str]]]:
    """(method, path template, regex of its paths) of every operation of the schema."""
    out = []
    for template, ops in schema["paths"].items():
        regex = re.compile("^" + re.sub(r"\\\{[^/]+?\\\}", "[^/]+", re.escape(template)) + "$")
        out += [(m.upper(), template, regex) for m in ops]
    return out


def test_rest_api_holds_to_its_openapi_schema(api: tuple[Deployment, str], tmp_path: Path) -> None:
    d, key = api
    config = tmp_path / "schemathesis.toml"
    config.write_text(CONFIG.format(seed=SEED, key=key, max_examples=MAX_EXAMPLES))
    report = tmp_path / "report"
    report_to = ["--report", "har", "--report-dir", str(report)]
    t0 = time.monotonic()
    r = subprocess.run(
        [*ST, "--no-color", "--config-file", str(config), "run", f"{d.url}/openapi.json", *report_to],
        capture_output=True,
        text=True,
        timeout=900,
        cwd=tmp_path,  # its cache (.schemathesis/) lands here, not in the checkout
    )
    took = time.monotonic() - t0
    out = (r.stdout + r.stderr).replace(key, "KEY")
    assert r.returncode == 0, f"schemathesis (seed {SEED}) found problems:\n{out[-30000:]}"

    schema = httpx.get(f"{d.url}/openapi.json").json()
    ops = operations(schema)
    (har,) = report.glob("*.json")
    entries = json.loads(har.read_text())["log"]["entries"]
    per_op: Counter[str] = Counter()
    for e in entries:
        method, path = e["request"]["method"], urlsplit(e["request"]["url"]).path
        hit = next((f"{m} {t}" for m, t, rx in ops if m == method and rx.match(path)), None)
        per_op[hit or f"{method} (no such operation: unsupported_method)"] += 1
    summary = ", ".join(f"{k}: {n}" for k, n in sorted(per_op.items()))
    print(f"schemathesis seed {SEED}: {len(entries)} requests in {took:.0f} s ({summary})")
    missing = {f"{m} {t}" for m, t, _ in ops} - set(per_op)
    assert not missing, f"operations never called: {missing}"
    assert len(entries) >= MIN_REQUESTS, (len(entries), summary)

    # the server came through it whole: ready, and nothing it did not expect in its log
    assert serving(httpx.get(f"{d.url}/readyz").json())  # no worker here: all but the workers' check
    log = (d.root / "server.log").read_text(errors="replace")
    assert "Traceback" not in log, log[-6000:]
