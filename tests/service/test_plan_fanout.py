"""A survey's plan spread over the workers (workers/photosteps.py): an 8-photo flight through Redis
and two workers has its plan features extracted in ``plan_features`` steps on both workers, each
photo's once, and is then planned as ``geomatch.pipeline`` plans it in one process (pairs and
turns); a chunk step run twice counts its photos once and queues the plan once."""

from __future__ import annotations

import hashlib
import json
import re
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from geomatch.features.store import FeatureStore
from geomatch.matching.stored import build_matcher
from geomatch.pipeline.prepare import frames, plan_project
from geomatch.pipeline.project import PlanRequest, ProjectImages
from geomatch.synth.flight import write_flight
from geomatch_core import jobstate
from geomatch_core.config import Settings
from geomatch_core.locks import FileLocks
from geomatch_core.models import Image, Job, JobPhoto, Project, Tenant
from geomatch_core.queue import PLAN_FEATURES, PLAN_MATCH
from geomatch_core.storage import Storage
from geomatch_core.store import MetadataStore
from workers import photosteps, runtime
from workers.context import StepContext

from .harness import Deployment, deployed, upload, wait_job

pytestmark = pytest.mark.service

PHOTOS = 8
CONFIG = {"resize": 320}  # the service is under test here: small photos keep the networks short
CHUNK_LOG = re.compile(r"plan features: chunk (\d+), (\d+) photos, (\d+) features computed")
PLAN_LOG = re.compile(r"planned \d+ pairs .* (\d+) features computed")


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("fanout-flight")
    write_flight(d, photos=PHOTOS, size=(320, 240), seed=5)
    return d / "images"


def reference_plan(images: Path, store_root: Path) -> tuple[dict[str, Any], int]:
    """The plan ``geomatch.pipeline`` makes of the photos in one process, and how many features it
    computed (a fresh store)."""
    names = sorted(p.name for p in images.iterdir())
    opts = runtime.job_options(CONFIG)
    store = FeatureStore(store_root)
    matcher = build_matcher(store, method=opts["method"], resize=opts["resize"], device="cpu")
    plan = plan_project(
        ProjectImages.read(images, names),
        dict.fromkeys(names, "auto"),
        PlanRequest(opts["pairs"], None, opts["tiling"]),
        lambda: matcher,
        frames(images, 256),
    )
    return plan.to_json(), store.saved


def test_a_survey_plan_runs_on_every_worker_and_plans_as_one_process(
    tmp_path: Path, redis_url: str, flight: Path
) -> None:
    with deployed(Deployment(tmp_path / "d", redis_url), workers=2) as d, d.client(d.create_key("fan")) as c:
        pid = c.post("/v1/projects", json={"name": "fanout", "config": CONFIG}).json()["id"]
        assert upload(c, pid, sorted(flight.iterdir())).status_code == 201
        r = c.post(f"/v1/projects/{pid}/match", json={})
        assert r.status_code == 202, r.text
        job = wait_job(c, r.json()["job_id"], timeout=1800)
        assert job["state"] == "succeeded", (job, d.logs())
        served = json.loads((d.home / "projects" / pid / "plan.json").read_text())
        logs = {w: (d.root / f"worker-{w}.log").read_text(errors="replace") for w in (0, 1)}

    chunks = {w: [tuple(map(int, m)) for m in CHUNK_LOG.findall(text)] for w, text in logs.items()}
    assert all(chunks.values()), f"a worker ran no plan_features step: {chunks}\n{logs}"
    done = [chunk for ran in chunks.values() for chunk in ran]
    assert sorted(ch for ch, _, _ in done) == list(range(len(done)))  # each chunk once
    assert sum(n for _, n, _ in done) == PHOTOS
    planned = [int(n) for text in logs.values() for n in PLAN_LOG.findall(text)]
    assert len(planned) == 1, logs  # one plan step, after the chunks

    expected, computed = reference_plan(flight, tmp_path / "reference-features")
    assert served == expected
    assert any(p["turns"] is not None for p in served["pairs"])  # a survey: the turns were decided
    # every feature the plan reads computed once: by the chunk steps, the plan step finding them
    assert sum(f for _, _, f in done) + planned[0] == computed


# -- a chunk step delivered twice -------------------------------------------------------------------
class RecordingQueue:
    """The steps queued, in order, run by nobody: the test runs them."""

    def __init__(self) -> None:
        self.queued: list[tuple[str, tuple[Any, ...]]] = []

    def enqueue(self, step: str, *args: Any) -> None:
        self.queued.append((step, args))

    def call(self, step: str, *args: Any, timeout: float) -> Any:
        raise NotImplementedError

    def ping(self) -> None:
        pass

    def slots(self) -> int:
        return 2

    def workers_alive(self) -> int | None:
        return None

    def close(self) -> None:
        pass


@pytest.fixture
def context(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[StepContext]:
    monkeypatch.setenv("GEOMATCH_HOME", str(tmp_path / "home"))
    monkeypatch.delenv("REDIS_URL", raising=False)
    monkeypatch.delenv("DATABASE_URL", raising=False)
    settings = Settings.from_env()
    storage = Storage(settings.home)
    store = MetadataStore(settings.database_url)
    store.create_all()
    yield StepContext(settings, store, storage, FileLocks(storage.writer_lock_path), RecordingQueue())
    store.dispose()


def survey_job(ctx: StepContext, flight: Path) -> str:
    """A running match job over the flight's photos, their files where the workers read them."""
    names = sorted(p.name for p in flight.iterdir())
    with ctx.store.session() as s:
        t = Tenant(name=f"t-{uuid.uuid4().hex[:6]}")
        s.add(t)
        s.flush()
        p = Project(tenant_id=t.id, name="p", config=CONFIG)
        s.add(p)
        s.flush()
        s.add_all(
            Image(
                project_id=p.id,
                name=n,
                sha256=hashlib.sha256((flight / n).read_bytes()).hexdigest(),
                width=320,
                height=240,
                size_bytes=(flight / n).stat().st_size,
                format="JPEG",
                capture="auto",
            )
            for n in names
        )
        j = Job(project_id=p.id, tenant_id=t.id, kind="match", options=CONFIG)
        s.add(j)
        s.flush()
        job_id, pid = j.id, p.id
    folder = ctx.storage.images_dir(pid)
    folder.mkdir(parents=True, exist_ok=True)
    for n in names:
        (folder / n).write_bytes((flight / n).read_bytes())
    return job_id


def test_a_chunk_step_run_twice_counts_its_photos_once_and_queues_the_plan_once(
    context: StepContext, flight: Path
) -> None:
    ctx, queue = context, context.queue
    assert isinstance(queue, RecordingQueue)
    job_id = survey_job(ctx, flight)
    job = jobstate.claim(ctx.store, job_id)
    assert job is not None and not photosteps.ready(ctx, job)
    chunks = [args[1] for step, args in queue.queued if step == PLAN_FEATURES]
    assert len(chunks) == 2 * queue.slots() and all(step == PLAN_FEATURES for step, _ in queue.queued)
    assert not photosteps.ready(ctx, job)  # a redelivered plan_match: the same chunks again, no rows
    assert [args[1] for _, args in queue.queued[len(chunks) :]] == chunks
    with ctx.store.session() as s:
        assert s.query(JobPhoto).filter_by(job_id=job_id).count() == PHOTOS
    queue.queued.clear()

    for chunk in chunks[:-1]:
        assert photosteps.plan_features(ctx, job_id, chunk) == "done"
        assert photosteps.plan_features(ctx, job_id, chunk) == "done before"  # delivered twice
    assert queue.queued == []  # photos left: no plan yet
    last = chunks[-1]
    assert photosteps.plan_features(ctx, job_id, last) == "done"
    assert queue.queued == [(PLAN_MATCH, (job_id,))]
    assert photosteps.plan_features(ctx, job_id, last) == "done before"
    assert jobstate.mark_photos_done(ctx.store, job_id, last) is None  # counted once
    assert queue.queued == [(PLAN_MATCH, (job_id,))]  # queued once
    with ctx.store.session() as s:
        assert s.query(JobPhoto).filter_by(job_id=job_id, done=False).count() == 0
    assert photosteps.ready(ctx, job)  # the plan step goes on to plan
    assert queue.queued == [(PLAN_MATCH, (job_id,))]
