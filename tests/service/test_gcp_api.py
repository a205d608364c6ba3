"""Ground control points over REST and gRPC (PUT / GET / DELETE .../gcp, PutGcp / GetGcp / DeleteGcp),
and a reconstruct job that georeferences the model by them and judges it at check points.

One `geomatch serve` for the module, in the embedded default (no Redis: HTTP and gRPC in one
process, jobs on its own threads). The GCP file is the synthetic scene's own (geomatch.synth.gcps:
exact pixels of ground points in the ground views the project holds), plus an observation in a
photo the project does not have, which must be reported, not refused.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import grpc
import httpx
import pytest

from geomatch.synth.aerial import Scene
from geomatch.synth.gcps import scene_gcps

from ..fswatch import watched
from ..test_gcp_hostile import generated_first_lines, hostile, make_targets
from .conftest import SCENE_SEED
from .grpc_harness import GrpcDeployment, error_of, running_grpc
from .harness import upload, wait_job

pytestmark = pytest.mark.service

# four ground views: six pairs, matched at 320 px in ~25 s; the global mapper registers all four
# (three views, or the incremental mapper, leave a model too weak to place the points)
GROUND = ["ground_00.png", "ground_01.png", "ground_02.png", "ground_03.png"]
N_POINTS = 8
ELSEWHERE = "aerial_00.png"  # a photo of the scene the projects here do not hold


@pytest.fixture(scope="module")
def dep(tmp_path_factory: pytest.TempPathFactory) -> Iterator[GrpcDeployment]:
    with running_grpc(tmp_path_factory.mktemp("gcp"), None, "serve") as d:
        yield d


@pytest.fixture(scope="module")
def key(dep: GrpcDeployment) -> str:
    return dep.create_key("surveyor")


@pytest.fixture(scope="module")
def gcp_list() -> str:
    """The points seen by two or more of GROUND, and one more line in a photo not in the project."""
    scene = Scene(SCENE_SEED)
    cams = [c for c in scene.cameras(2, 4, 640, 480) if c.name in GROUND]  # conftest's scene
    text, _ = scene_gcps(scene, cams, N_POINTS, seed=3)
    return text + f"465000.0 5247000.0 408.0 320.0 240.0 {ELSEWHERE} gcp00\n"


def project(c: httpx.Client, scene: Path, name: str) -> str:
    pid = str(c.post("/v1/projects", json={"name": name}).json()["id"])
    assert upload(c, pid, [scene / "images" / n for n in GROUND], "ground").status_code == 201
    return pid


def stored(dep: GrpcDeployment, pid: str) -> bytes | None:
    path = dep.home / "projects" / pid / "gcp_list.txt"
    return path.read_bytes() if path.exists() else None


def check_summary(s: dict[str, Any]) -> None:
    assert s["crs"] == "EPSG:32632" and s["frame"] == "EPSG:32632", s
    assert s["points"] == [f"gcp{i:02d}" for i in range(N_POINTS)], s
    assert any(f"image '{ELSEWHERE}' is not in the project" in p for p in s["problems"]), s
    assert s["unusable"] == {} and s["error"] is None, s


def test_rest_put_get_replace_delete(dep: GrpcDeployment, key: str, scene: Path, gcp_list: str) -> None:
    c = dep.client(key)
    pid = project(c, scene, "gcp-rest")
    assert c.get(f"/v1/projects/{pid}/gcp").status_code == 404  # none yet

    r = c.put(f"/v1/projects/{pid}/gcp", content=gcp_list, headers={"content-type": "text/plain"})
    assert r.status_code == 200, r.text
    check_summary(r.json())
    assert r.json()["size_bytes"] == len(gcp_list.encode())
    assert c.get(f"/v1/projects/{pid}/gcp").json() == r.json()
    assert stored(dep, pid) == gcp_list.encode()

    # a multipart upload, as the images route takes files, replaces it
    fewer = "\n".join(ln for ln in gcp_list.splitlines() if "gcp05" not in ln) + "\n"
    r = c.put(f"/v1/projects/{pid}/gcp", files={"file": ("gcp_list.txt", fewer.encode(), "text/plain")})
    assert r.status_code == 200, r.text
    assert r.json()["points"] == [f"gcp{i:02d}" for i in range(N_POINTS) if i != 5]
    assert stored(dep, pid) == fewer.encode()
    # as `curl --data-binary @gcp_list.txt` sends it, unless told the type
    form = {"content-type": "application/x-www-form-urlencoded"}
    assert c.put(f"/v1/projects/{pid}/gcp", content=fewer, headers=form).json() == r.json()

    other = dep.client(dep.create_key("someone-else"))
    assert other.get(f"/v1/projects/{pid}/gcp").status_code == 404  # another tenant's project
    assert other.put(f"/v1/projects/{pid}/gcp", content=gcp_list).status_code == 404
    assert other.delete(f"/v1/projects/{pid}/gcp").status_code == 404
    assert stored(dep, pid) == fewer.encode()

    assert c.delete(f"/v1/projects/{pid}/gcp").status_code == 204
    assert stored(dep, pid) is None
    assert c.get(f"/v1/projects/{pid}/gcp").status_code == 404
    assert c.delete(f"/v1/projects/{pid}/gcp").status_code == 404


def test_rest_refuses_a_bad_file_with_the_reason_and_keeps_the_earlier(
    dep: GrpcDeployment, key: str, scene: Path, gcp_list: str
) -> None:
    c = dep.client(key)
    pid = project(c, scene, "gcp-bad")
    good = c.put(f"/v1/projects/{pid}/gcp", content=gcp_list).json()
    others = "".join(f"465000 524700{i} 408 10 10 {n} p{i}\n" for i in range(3) for n in ("x.png", "y.png"))
    bad: list[tuple[bytes, int, str]] = [
        (b"NAD99 / nowhere\n1 2 3 4 5 ground_00.png a\n", 422, "line 1: unknown coordinate system"),
        # every point in photos the project does not hold: the reason names them
        (("EPSG:32632\n" + others).encode(), 422, "line 2: p0: image 'x.png' is not in the project"),
        # one observation each: no point can be placed
        (b"EPSG:32632\n465000 5247000 408 10 10 ground_00.png a\n", 422, "a: seen in one photo only"),
        (b"EPSG:32632\n465000 5247000 408 -50 10 ground_00.png a\n", 422, "pixel (-50, 10) is outside"),
        (b"", 422, "no GCP file"),
        ("EPSG:32632\n\xe9t\xe9\n".encode("latin-1"), 400, "not UTF-8 text (line 2"),
        (b"EPSG:32632\n# " + b"x" * (1 << 20), 413, "over the limit of 1 MiB"),
        (b"# " + b"x" * (2 << 20), 413, "a GCP file over 1 MiB"),  # refused before it is read
    ]
    for body, status, reason in bad:
        r = c.put(f"/v1/projects/{pid}/gcp", content=body, headers={"content-type": "text/plain"})
        assert r.status_code == status and reason in r.json()["detail"], (body[:60], r.status_code, r.text)
        assert c.get(f"/v1/projects/{pid}/gcp").json() == good  # the earlier file stays
        assert stored(dep, pid) == gcp_list.encode()
    r = c.put(f"/v1/projects/{pid}/gcp", content=b"{}", headers={"content-type": "application/json"})
    assert r.status_code == 415 and "multipart field 'file'" in r.json()["detail"], r.text
    assert c.put("/v1/projects/" + "0" * 32 + "/gcp", content=gcp_list).status_code == 404
    assert not [p.name for p in (dep.home / "tmp").glob("upload-*")]  # no temporary left behind

    # refused on a project without one: still none
    c.delete(f"/v1/projects/{pid}/gcp")
    r = c.put(f"/v1/projects/{pid}/gcp", content=bad[0][0])
    assert r.status_code == 422 and stored(dep, pid) is None


def test_hostile_coordinate_systems_are_refused_open_nothing_and_leave_health_answering(
    dep: GrpcDeployment, key: str, scene: Path, gcp_list: str, tmp_path: Path
) -> None:
    """Line 1 naming files (a secret, /etc/shadow, a FIFO, /dev/kmsg), grids, URLs, another planet:
    422 / INVALID_ARGUMENT naming line 1 over REST and gRPC, the earlier file kept, no file under
    the watched folder opened by the server, and /healthz and gRPC health answering after each."""
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    c = dep.client(key)
    pid = project(c, scene, "gcp-hostile")
    assert c.put(f"/v1/projects/{pid}/gcp", content=gcp_list).status_code == 200
    targets = make_targets(tmp_path / "targets")
    points = gcp_list.split("\n", 1)[1]
    with (
        watched(tmp_path / "targets") as seen,
        dep.grpc_client(key, timeout=30) as g,
        grpc.insecure_channel(dep.target) as ch,
    ):
        health = health_pb2_grpc.HealthStub(ch)
        for crs in hostile(targets):
            body = f"{crs}\n{points}"
            r = c.put(f"/v1/projects/{pid}/gcp", content=body, headers={"content-type": "text/plain"})
            assert r.status_code == 422 and r.json()["detail"].startswith("line 1: "), (crs[:80], r.text)
            code, message = error_of(lambda body=body: g.put_gcp(pid, body))
            assert code == grpc.StatusCode.INVALID_ARGUMENT and message.startswith("line 1: "), message
            assert httpx.get(f"{dep.url}/healthz", timeout=2).status_code == 200
            answer = health.Check(health_pb2.HealthCheckRequest(service=""), timeout=2)
            assert answer.status == health_pb2.HealthCheckResponse.SERVING
    assert seen == [], seen
    assert stored(dep, pid) == gcp_list.encode()
    assert c.get(f"/v1/projects/{pid}/gcp").json()["crs"] == "EPSG:32632"


def test_generated_first_lines_never_fail_inside_the_server(
    dep: GrpcDeployment, key: str, scene: Path, gcp_list: str
) -> None:
    """Generated coordinate systems (file-naming parameters, paths, URLs, WKT fragments, other
    authorities, control characters) over REST and gRPC: 200 or a 4xx / INVALID_ARGUMENT with a
    message, never a server error; the GET of what was stored answers too."""
    c = dep.client(key)
    pid = project(c, scene, "gcp-generated")
    assert c.put(f"/v1/projects/{pid}/gcp", content=gcp_list).status_code == 200
    points = gcp_list.split("\n", 1)[1]
    statuses: list[int] = []
    with dep.grpc_client(key, timeout=30) as g:
        for crs in generated_first_lines(2, 60):
            body = f"{crs}\n{points}"
            r = c.put(
                f"/v1/projects/{pid}/gcp", content=body.encode(), headers={"content-type": "text/plain"}
            )
            statuses.append(r.status_code)
            assert r.status_code in (200, 400, 422), (crs, r.status_code, r.text)
            if r.status_code != 200:
                assert r.json()["detail"], r.text
            assert c.get(f"/v1/projects/{pid}/gcp").status_code == 200
            try:
                g.put_gcp(pid, body)
            except grpc.RpcError as e:
                assert e.code() == grpc.StatusCode.INVALID_ARGUMENT and e.details(), (
                    crs,
                    e.code(),
                    e.details(),
                )
    print(f"generated first lines: {statuses.count(200)} read, {len(statuses) - statuses.count(200)} refused")


def test_grpc_put_get_delete(dep: GrpcDeployment, key: str, scene: Path, gcp_list: str) -> None:
    pid = project(dep.client(key), scene, "gcp-grpc")
    with dep.grpc_client(key, timeout=60) as g:
        s = g.put_gcp(pid, gcp_list)
        check_summary(
            {
                "crs": s.crs,
                "frame": s.frame,
                "points": list(s.points),
                "problems": list(s.problems),
                "unusable": dict(s.unusable),
                "error": s.error if s.HasField("error") else None,
            }
        )
        assert s.size_bytes == len(gcp_list.encode())
        assert g.get_gcp(pid) == s
        assert dep.client(key).get(f"/v1/projects/{pid}/gcp").json()["points"] == list(s.points)  # one file

        code, message = error_of(lambda: g.put_gcp(pid, "NAD99\n1 2 3 4 5 ground_00.png a\n"))
        assert code == grpc.StatusCode.INVALID_ARGUMENT and "line 1: unknown coordinate system" in message
        code, message = error_of(lambda: g.put_gcp(pid, "EPSG:32632\n" + "# x\n" * (1 << 18) + "\n"))
        assert code == grpc.StatusCode.RESOURCE_EXHAUSTED and "over the limit of 1 MiB" in message
        assert g.get_gcp(pid) == s and stored(dep, pid) == gcp_list.encode()
        assert error_of(lambda: g.put_gcp("0" * 32, gcp_list))[0] == grpc.StatusCode.NOT_FOUND

        g.delete_gcp(pid)
        assert error_of(lambda: g.get_gcp(pid))[0] == grpc.StatusCode.NOT_FOUND
        assert error_of(lambda: g.delete_gcp(pid))[0] == grpc.StatusCode.NOT_FOUND
    with dep.grpc_client(dep.create_key("grpc-other"), timeout=60) as other:
        assert error_of(lambda: other.put_gcp(pid, gcp_list))[0] == grpc.StatusCode.NOT_FOUND


def test_reconstruct_georeferences_by_the_gcps_and_judges_at_the_check_points(
    dep: GrpcDeployment, key: str, scene: Path, gcp_list: str
) -> None:
    """Images and GCPs in, match, reconstruct with check points: the job's result carries ``gcp``
    (residuals, check-point RMSE) and the model is in the points' frame."""
    t0 = time.monotonic()
    c = dep.client(key)
    pid = project(c, scene, "gcp-e2e")
    assert c.put(f"/v1/projects/{pid}/gcp", content=gcp_list).status_code == 200
    match = wait_job(c, c.post(f"/v1/projects/{pid}/match", json={"resize": 320}).json()["job_id"])
    assert match["state"] == "succeeded", (match, dep.logs())
    r = c.get(f"/v1/projects/{pid}/report")  # matched, not reconstructed: no report yet
    assert r.status_code == 404 and "has no model yet" in r.json()["detail"], r.text

    # check points are checked against the file before a job is queued
    for bad, reason in [
        (["gcp99"], "not among the usable GCPs: gcp99"),
        (N_POINTS - 2, "leave fewer than 3 control points"),
        (-1, "greater than or equal to 0"),
        (["gcp01", "gcp01"], "named twice"),
    ]:
        r = c.post(f"/v1/projects/{pid}/reconstruct", json={"checkpoints": bad})
        assert r.status_code == 422 and reason in r.text, (bad, r.text)
    with dep.grpc_client(key, timeout=60) as g:
        code, message = error_of(lambda: g.submit_reconstruction(pid, checkpoints=["gcp99"]))
        assert code == grpc.StatusCode.INVALID_ARGUMENT and "gcp99" in message
    assert [j["kind"] for j in c.get(f"/v1/projects/{pid}/jobs").json()["jobs"]] == ["match"]

    r = c.post(f"/v1/projects/{pid}/reconstruct", json={"checkpoints": 2, "mapper": "global"})
    assert r.status_code == 202, r.text
    recon = wait_job(c, r.json()["job_id"])
    assert recon["state"] == "succeeded", (recon, dep.logs())
    assert recon["options"]["checkpoints"] == 2
    result = recon["result"]
    g = result["gcp"]
    assert "error" not in g, g
    assert result["frame"] == "GCP" and result["georeferenced"] is True
    roles = {p["name"]: p["role"] for p in g["points"]}
    assert sorted(roles.values()).count("check") == 2 and sorted(roles.values()).count("control") >= 3, g
    assert any(ELSEWHERE in p for p in g["problems"]), g
    # the ground views see these points 10-30 m away, matched at 320 px: 0.16 m check RMSE measured
    assert 0 <= g["check_rmse_3d_m"] < 1.0 and g["control_rmse_3d_m"] < 0.5, g
    # the job's result is the survey report too, with the same check points
    assert result["report"]["georeferencing"]["gcp"]["check_rmse_3d_m"] == g["check_rmse_3d_m"]
    assert result["report"]["photos"]["registered"] == result["registered"]
    assert c.get(f"/v1/projects/{pid}/model", params={"format": "json"}).json() == result
    check_report_endpoint(dep, c, pid, result)
    print(
        f"GCP end to end: {time.monotonic() - t0:.0f} s, check RMSE 3D {g['check_rmse_3d_m']} m, "
        f"control {g['control_rmse_3d_m']} m"
    )


def check_report_endpoint(dep: GrpcDeployment, c: httpx.Client, pid: str, result: dict[str, Any]) -> None:
    """GET .../report: the job's report as JSON, the Markdown page with the check points, another
    tenant's 404, and the report of a model from before reports, built from its summary."""
    r = c.get(f"/v1/projects/{pid}/report")
    assert r.status_code == 200 and r.headers["content-type"] == "application/json", r.text
    assert r.json() == result["report"]
    assert c.get(f"/v1/projects/{pid}/report", params={"format": "json"}).json() == result["report"]
    md = c.get(f"/v1/projects/{pid}/report", params={"format": "md"})
    assert md.status_code == 200 and md.headers["content-type"] == "text/markdown; charset=utf-8"
    gcp = result["report"]["georeferencing"]["gcp"]
    assert md.text.startswith("# Survey report: gcp-e2e\n"), md.text
    assert f"- registered: {result['registered']} of {len(GROUND)}" in md.text
    rmse = f"{gcp['check_rmse_horizontal_m']} m horizontal, {gcp['check_rmse_3d_m']} m 3D"
    assert f"- check-point RMSE: {rmse}" in md.text, md.text
    assert sum(line.startswith("| gcp0") for line in md.text.splitlines()) == len(gcp["points"])
    assert c.get(f"/v1/projects/{pid}/report", params={"format": "pdf"}).status_code == 422
    assert dep.client(dep.create_key("report-other")).get(f"/v1/projects/{pid}/report").status_code == 404

    summary = dep.home / "projects" / pid / "model" / "summary.json"
    older = {k: v for k, v in result.items() if k != "report"}
    summary.write_text(json.dumps(older))
    assert c.get(f"/v1/projects/{pid}/report").json() == result["report"]
