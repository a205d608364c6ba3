"""A project's jobs as the server keeps them: ``GET /v1/projects/{id}/jobs`` and gRPC's ``ListJobs``
list the running and past jobs of a project to any client of its tenant (a second browser tab, a
phone, a script), newest first, in pages, optionally of one state; another tenant's project is a
404 / NOT_FOUND as on every other route.

One `geomatch serve` (REST and gRPC) per metadata store, Redis mode with no worker: the jobs stay
queued until cancelled, so what each list holds is known exactly."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import grpc
import pytest

from service.grpcapi.pb import pb2

from .grpc_harness import error_of, serving_on_store
from .harness import noise_project

pytestmark = pytest.mark.service


@pytest.fixture(scope="module", params=["sqlite", "postgresql"])
def world(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory, redis_url: str
) -> Iterator[dict[str, Any]]:
    """A server; a project with two images and four jobs, started in this order: match A, match B
    (with the reconstruct it queues behind it), match C, which was then cancelled."""
    with serving_on_store(tmp_path_factory.mktemp(f"jobs-{request.param}"), redis_url, request.param) as d:
        key = d.create_key("jobs")
        with d.client(key) as c:
            pid = noise_project(c, "jobs")
            a = c.post(f"/v1/projects/{pid}/match", json={}).json()["job_id"]
            b = c.post(f"/v1/projects/{pid}/match", json={"reconstruct": True}).json()
            cancelled = c.post(f"/v1/projects/{pid}/match", json={}).json()["job_id"]
            assert c.delete(f"/v1/jobs/{cancelled}").json()["state"] == "cancelled"
        newest_first = [cancelled, b["reconstruct_job_id"], b["job_id"], a]
        yield {"d": d, "key": key, "pid": pid, "jobs": newest_first}


def test_rest_lists_a_projects_jobs_newest_first_in_pages(world: dict[str, Any]) -> None:
    d, pid, jobs = world["d"], world["pid"], world["jobs"]
    with d.client(world["key"]) as c:
        r = c.get(f"/v1/projects/{pid}/jobs")
        assert r.status_code == 200, r.text
        listed = r.json()["jobs"]
        assert [j["id"] for j in listed] == jobs
        assert "next" not in r.links
        # each as GET /v1/jobs/{id} shows it: state, progress and the rest
        for j in listed:
            assert j == c.get(f"/v1/jobs/{j['id']}").json()
        assert [(j["kind"], j["state"]) for j in listed] == [
            ("match", "cancelled"),
            ("reconstruct", "queued"),
            ("match", "queued"),
            ("match", "queued"),
        ]
        assert listed[1]["after_job_id"] == jobs[2]

        seen, url = [], f"/v1/projects/{pid}/jobs?limit=3"
        while url:
            r = c.get(url)
            assert r.status_code == 200 and len(r.json()["jobs"]) <= 3
            seen += [j["id"] for j in r.json()["jobs"]]
            url = r.links.get("next", {}).get("url", "")
        assert seen == jobs
        assert c.get(f"/v1/projects/{pid}/jobs?limit=1001").status_code == 422

        # one state; the filter stays in the next page's link
        r = c.get(f"/v1/projects/{pid}/jobs?state=queued&limit=2")
        assert [j["id"] for j in r.json()["jobs"]] == jobs[1:3]
        assert [j["id"] for j in c.get(r.links["next"]["url"]).json()["jobs"]] == jobs[3:]
        assert [j["id"] for j in c.get(f"/v1/projects/{pid}/jobs?state=cancelled").json()["jobs"]] == jobs[:1]
        assert c.get(f"/v1/projects/{pid}/jobs?state=running").json() == {"jobs": []}
        assert c.get(f"/v1/projects/{pid}/jobs?state=done").status_code == 422

        # a project without jobs, an unknown one, a deleted one
        empty = c.post("/v1/projects", json={"name": "no jobs"}).json()["id"]
        assert c.get(f"/v1/projects/{empty}/jobs").json() == {"jobs": []}
        assert c.get(f"/v1/projects/{'0' * 32}/jobs").status_code == 404
        assert c.delete(f"/v1/projects/{empty}").status_code == 204
        assert c.get(f"/v1/projects/{empty}/jobs").status_code == 404

    # another tenant's project is not found, as on every route
    with d.client(d.create_key("jobs-other")) as o:
        r = o.get(f"/v1/projects/{pid}/jobs")
        assert r.status_code == 404 and r.json()["detail"] == f"project {pid} not found"


def test_grpc_list_jobs_is_the_same_list(world: dict[str, Any]) -> None:
    d, pid, jobs = world["d"], world["pid"], world["jobs"]
    with d.grpc_client(world["key"], timeout=30) as g:

        def page(**fields: Any) -> Any:
            return g.stub.ListJobs(
                pb2.ListJobsRequest(project_id=pid, **fields), metadata=g.metadata, timeout=10
            )

        first = page(page_size=3)
        assert [j.id for j in first.jobs] == jobs[:3] and first.next_page_token
        rest = page(page_size=3, page_token=first.next_page_token)
        assert [j.id for j in rest.jobs] == jobs[3:] and rest.next_page_token == ""
        assert [j.kind for j in first.jobs] == [
            pb2.JOB_KIND_MATCH,
            pb2.JOB_KIND_RECONSTRUCT,
            pb2.JOB_KIND_MATCH,
        ]
        assert first.jobs[0].state == pb2.JOB_STATE_CANCELLED
        assert first.jobs[0] == g.get_job(jobs[0])

        assert [j.id for j in g.list_jobs(pid)] == jobs
        assert [j.id for j in g.list_jobs(pid, state="queued")] == jobs[1:]
        assert [j.id for j in page(state=pb2.JOB_STATE_CANCELLED).jobs] == jobs[:1]
        assert list(page(state=pb2.JOB_STATE_RUNNING).jobs) == []

        code, _ = error_of(lambda: page(page_token="nope"))
        assert code == grpc.StatusCode.INVALID_ARGUMENT
        code, details = error_of(lambda: page(state=99))
        assert code == grpc.StatusCode.INVALID_ARGUMENT, details
        code, _ = error_of(lambda: g.list_jobs("0" * 32))
        assert code == grpc.StatusCode.NOT_FOUND
    with d.grpc_client(d.create_key("jobs-grpc-other"), timeout=30) as o:
        code, details = error_of(lambda: o.list_jobs(pid))
        assert code == grpc.StatusCode.NOT_FOUND and details == f"project {pid} not found"
