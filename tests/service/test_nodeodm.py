"""The NodeODM node, with PyODM (the version WebODM pins) as its client: a real `geomatch serve`
with its node on a port of its own, one `geomatch worker`, real Redis, and the small synthetic
scene's four ground photos (each with a GPS fix) plus a GCP file made for them.

One task runs to the end and the tests read it: what WebODM reads of the node (/info, /options
built into NodeOption as WebODM builds them), the task's codes and progress while it runs, its
console, its assets (the LAZ read back with laspy and held to the model's points), a chunked Range
download, a restart with options; another task is cancelled and removed; and bad input (token,
uuid, option value, a corrupt image, a GCP file that does not parse) is an error PyODM raises as
NodeResponseError, from an HTTP 200, never a 5xx."""

from __future__ import annotations

import io
import json
import time
import uuid
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import laspy
import numpy as np
import pycolmap
import pytest
from pyodm import Node
from pyodm.api import Task
from pyodm.exceptions import NodeResponseError, TaskFailedError
from pyodm.types import NodeOption, TaskInfo, TaskStatus

from geomatch.synth.aerial import Scene, write_scene
from geomatch.synth.gcps import scene_gcps

from .harness import Deployment, deployed

pytestmark = pytest.mark.service

# what a drone team would pick for a small job, and an option of ODM's that geomatch does not know
OPTIONS = {"method": "sparse", "resize": 480, "pairs": "exhaustive", "checkpoints": 1, "dsm": True}


@dataclass
class Run:
    task: Task
    seen: list[TaskInfo] = field(default_factory=list)
    info_s: list[float] = field(default_factory=list)  # how long /info took while the task ran


@pytest.fixture(scope="module")
def photos(tmp_path_factory: pytest.TempPathFactory) -> list[str]:
    """The scene's 4 ground photos (GPS fixes with 0.5 m noise) and a gcp_list.txt of 6 points
    clicked in them (EPSG:32632)."""
    d = tmp_path_factory.mktemp("node-scene")
    cams = write_scene(d, 2, 4, seed=1, gps_noise=0.5)
    ground = [c for c in cams if c.name.startswith("ground")]
    text, _ = scene_gcps(Scene(1), ground, 6, seed=1)
    (d / "gcp_list.txt").write_text(text)
    return [str(d / "images" / c.name) for c in ground] + [str(d / "gcp_list.txt")]


@pytest.fixture(scope="module")
def deployment(tmp_path_factory: pytest.TempPathFactory, redis_url: str) -> Iterator[Deployment]:
    with deployed(Deployment(tmp_path_factory.mktemp("nodeodm"), redis_url), node=True) as d:
        yield d


@pytest.fixture(scope="module")
def key(deployment: Deployment) -> str:
    return deployment.create_key("drone-team")


@pytest.fixture(scope="module")
def node(deployment: Deployment, key: str) -> Node:
    return Node("127.0.0.1", deployment.node_port, token=key)


def node_url(deployment: Deployment, path: str, key: str) -> str:
    return f"http://127.0.0.1:{deployment.node_port}{path}?token={key}"


@pytest.fixture(scope="module")
def done(node: Node, photos: list[str]) -> Run:
    task = node.create_task(photos, OPTIONS, name="field survey")
    run = Run(task)

    def seen(info: TaskInfo) -> None:
        run.seen.append(info)
        t0 = time.perf_counter()
        node.info()
        run.info_s.append(time.perf_counter() - t0)

    task.wait_for_completion(status_callback=seen, interval=1)
    return run


def test_info_and_options_as_webodm_reads_them(node: Node, deployment: Deployment, key: str) -> None:
    info = node.info()
    parts = info.version.split(".")
    assert len(parts) == 3 and all(p.isdigit() for p in parts) and tuple(map(int, parts)) >= (1, 5, 1)
    assert isinstance(info.task_queue_count, int) and info.max_images is None
    assert info.engine == "geomatch" and 0 < len(info.engine_version) <= 32
    assert info.max_parallel_tasks >= 1 and info.cpu_cores >= 1 and info.total_memory > 0
    raw = httpx.get(node_url(deployment, "/options", key)).json()
    assert all(set(o) == {"name", "type", "value", "domain", "help"} for o in raw)  # NodeOption(**o)
    options = {o.name: o for o in (NodeOption(**o) for o in raw)}
    assert {"pairs", "method", "resize", "tiling", "mapper", "checkpoints"} <= set(options)
    assert options["method"].type == "enum" and "sparse" in options["method"].domain
    assert options["resize"].type == "int" and options["resize"].value == "640"
    assert all(isinstance(o.value, str) for o in options.values())


def test_task_runs_to_completion_and_progress_never_goes_back(done: Run) -> None:
    codes = [i.status.value for i in done.seen]
    assert codes[-1] == 40 and set(codes) <= {10, 20, 40}, codes
    assert codes == sorted(codes), codes
    progress = [i.progress for i in done.seen]
    assert progress == sorted(progress) and progress[-1] == 100, progress
    info = done.task.info()
    assert info.images_count == 4 and info.name == "field survey" and info.processing_time > 0
    # the option geomatch does not know is dropped; the others are echoed as sent
    assert {o["name"] for o in info.options} == {"method", "resize", "pairs", "checkpoints"}
    # /info while the task was queued, matched and mapped: WebODM's refresh must never stall
    assert max(done.info_s) < 1.0, done.info_s


def test_console_output_by_line(done: Run) -> None:
    lines = done.task.info(with_output=0).output
    assert lines == done.task.output(0) and done.task.output(3) == lines[3:]
    assert any("reconstruction succeeded" in ln for ln in lines)
    assert any(ln.startswith("# Survey report: field survey") for ln in lines)


def test_assets_are_where_webodm_looks_and_the_laz_is_the_model(
    done: Run, deployment: Deployment, key: str, tmp_path: Path
) -> None:
    dest = Path(done.task.download_assets(str(tmp_path / "assets")))
    for f in (
        "odm_georeferencing/odm_georeferenced_model.laz",
        "odm_georeferencing/ground_control_points.geojson",
        "odm_report/shots.geojson",
        "odm_report/report.pdf",
        "odm_report/stats.json",
        "cameras.json",
        "images.json",
        "task_output.txt",
    ):
        assert (dest / f).is_file(), f
    summary = json.loads((dest / "summary.json").read_text())
    assert summary["frame"] == "GCP" and summary["gcp"]["frame"] == "EPSG:32632"
    las = laspy.read(dest / "odm_georeferencing" / "odm_georeferenced_model.laz")
    assert las.header.parse_crs().to_epsg() == 32632  # the GCP file's system
    assert len(las.points) == summary["points3D"]
    # the model as the REST API serves it, moved by the GCP frame's origin: the LAZ's points
    pid = uuid.UUID(done.task.uuid).hex
    with httpx.Client(base_url=deployment.url, headers={"Authorization": f"Bearer {key}"}) as c:
        r = c.get(f"/v1/projects/{pid}/model", params={"format": "zip"})
    assert r.status_code == 200
    zipfile.ZipFile(io.BytesIO(r.content)).extractall(tmp_path / "model")
    rec = pycolmap.Reconstruction(str(tmp_path / "model" / "sparse" / "0"))
    xyz = np.array([rec.points3D[i].xyz for i in sorted(rec.points3D)]) + summary["gcp"]["origin"]
    got = np.column_stack([las.x, las.y, las.z])
    np.testing.assert_allclose(np.sort(got, axis=0), np.sort(xyz, axis=0), atol=0.002)
    shots = json.loads((dest / "odm_report" / "shots.geojson").read_text())["features"]
    assert len(shots) == summary["registered"] == 4
    assert (dest / "odm_report" / "report.pdf").read_bytes().startswith(b"%PDF-")
    # the console's copy ends as the task's console does
    assert (dest / "task_output.txt").read_text().splitlines() == done.task.output(0)


def test_chunked_range_download_is_byte_identical(
    done: Run, deployment: Deployment, key: str, tmp_path: Path
) -> None:
    whole = httpx.get(node_url(deployment, f"/task/{done.task.uuid}/download/all.zip", key))
    assert whole.status_code == 200 and whole.headers["accept-ranges"] == "bytes"
    part = httpx.get(
        node_url(deployment, f"/task/{done.task.uuid}/download/all.zip", key),
        headers={"Range": "bytes=10-99"},
    )
    assert part.status_code == 206 and part.content == whole.content[10:100]
    # PyODM's parallel download: chunks of 4 KiB, fetched by Range requests and joined
    path = done.task.download_zip(str(tmp_path), parallel_downloads=4, parallel_chunks_size=1 / 256)
    assert len(whole.content) > 4 * 4096
    assert Path(path).read_bytes() == whole.content


def test_restart_with_options_runs_the_jobs_again(done: Run) -> None:
    assert done.task.restart({"mapper": "incremental"}) is True
    done.task.wait_for_completion(interval=1)
    info = done.task.info(with_output=0)
    assert info.status == TaskStatus.COMPLETED and info.options == [
        {"name": "mapper", "value": "incremental"}
    ]
    assert any(ln.startswith("[restart 1] reconstruction started (mapper incremental)") for ln in info.output)


def test_cancel_and_remove(node: Node, photos: list[str]) -> None:
    task = node.create_task(photos[:3], {"method": "sparse", "resize": 480})
    assert task.cancel() is True
    with pytest.raises(TaskFailedError):
        task.wait_for_completion(interval=1)
    assert task.info().status == TaskStatus.CANCELED
    assert task.remove() is True
    with pytest.raises(NodeResponseError):
        task.info()
    assert task.uuid not in {t["uuid"] for t in node.get("/task/list")}


def test_bad_input_is_a_node_error_never_a_server_error(
    node: Node, deployment: Deployment, key: str, photos: list[str], tmp_path: Path
) -> None:
    before = node.get("/task/list")
    with pytest.raises(NodeResponseError):
        Node("127.0.0.1", deployment.node_port, token="gm_not-a-key").info()
    with pytest.raises(NodeResponseError):
        Task(node, str(uuid.uuid4())).info()
    with pytest.raises(NodeResponseError, match="resize"):
        node.create_task(photos[:2], {"resize": 5})
    corrupt = tmp_path / "broken.png"
    corrupt.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 64)
    t0 = time.monotonic()
    with pytest.raises(NodeResponseError):
        node.create_task([photos[0], str(corrupt)], {"method": "sparse"})
    assert time.monotonic() - t0 < 20, "a refused file is not sent again"
    bad_gcp = tmp_path / "gcp_list.txt"
    bad_gcp.write_text("EPSG:32632\n1 2 3 not numbers here\n")
    with pytest.raises(NodeResponseError):
        node.create_task([*photos[:4], str(bad_gcp)], {"method": "sparse"})
    # the refused tasks are gone whole (the corrupt image is answered at the commit, which
    # removes the task: a refused upload would have PyODM send it five more times first)
    assert node.get("/task/list") == before
    # raw answers: HTTP 200 with {"error"} (PyODM and WebODM read anything else as a broken node)
    for method, path in (("GET", f"/task/{uuid.uuid4()}/info"), ("POST", "/task/cancel")):
        r = httpx.request(method, node_url(deployment, path, key), data={"uuid": "nope"})
        assert r.status_code == 200 and "error" in r.json(), (path, r.text)
    r = httpx.get(f"http://127.0.0.1:{deployment.node_port}/info?token=wrong")
    assert r.status_code == 200 and "error" in r.json()


def test_token_never_reaches_the_log(done: Run, deployment: Deployment, key: str) -> None:
    log = (deployment.root / "server.log").read_text()
    assert "token=***" in log and key not in log.replace(f"API key (tenant 'local'): {key}", "")
