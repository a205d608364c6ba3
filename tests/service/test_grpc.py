"""The gRPC API against real processes, Redis mode: ``python -m geomatch_app grpc-serve`` on a loopback port
and one ``geomatch worker``, real networks and pycolmap.

End to end on the synthetic scene (streamed upload, WatchJob, GetModel, every image registered);
every bad input of the REST tests mapped to its status code, plus the framing's own; a client that
disconnects mid-upload leaves nothing; two clients upload into one project at once; MatchPair runs
on the worker (the server process never loads torch) and honours deadlines; health, reflection,
auth and tenants.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import signal
import subprocess
import sys
import threading
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import grpc
import numpy as np
import pycolmap
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha.proto_reflection_descriptor_database import ProtoReflectionDescriptorDatabase

from service.clients.grpc_client import GrpcClient, ImageSource, to_dict
from service.grpcapi.pb import pb2

from ..small_scene import PAIRS  # the measured pair list (tests/small_scene.py)
from .grpc_harness import SERVED_METHODS, GrpcDeployment, code_of, error_of
from .harness import deployed
from .test_api import bad_files

pytestmark = pytest.mark.service

# The end-to-end run is about the service, not the matcher (tests/test_pipeline_e2e.py and the REST
# e2e run the paper's method on this scene): the sparse method at 480 px registers every image too
# (measured), at a fraction of the CPU. MatchPair below runs the default method, checked against
# the ground truth.
RESIZE, METHOD = 480, "sparse"
PAIR_RESIZE = 320
MiB = 1024 * 1024


@pytest.fixture(scope="module")
def dep(tmp_path_factory: pytest.TempPathFactory, redis_url: str) -> Iterator[GrpcDeployment]:
    """Uploads capped at 2 MiB, so the size limit is testable with small files."""
    with deployed(
        GrpcDeployment(tmp_path_factory.mktemp("grpc"), redis_url, GEOMATCH_MAX_UPLOAD_MB="2"), grpc="module"
    ) as d:
        yield d


@pytest.fixture(scope="module")
def key(dep: GrpcDeployment) -> str:
    return dep.create_key("grpc-a")


@pytest.fixture(scope="module")
def a(dep: GrpcDeployment, key: str) -> Iterator[GrpcClient]:
    with dep.grpc_client(key) as c:
        yield c


@pytest.fixture(scope="module")
def b(dep: GrpcDeployment) -> Iterator[GrpcClient]:
    with dep.grpc_client(dep.create_key("grpc-b")) as c:
        yield c


@pytest.fixture(scope="module")
def project(a: GrpcClient, scene: Path) -> str:
    """A project with one image, for the requests that must be refused."""
    p = a.create_project("refusals")
    a.upload(p.id, [ImageSource.of(scene / "images" / "ground_00.png", "ground")])
    return str(p.id)


def raw_upload(c: GrpcClient, messages: list[Any], timeout: float = 60) -> Any:
    return c.stub.UploadImages(iter(messages), metadata=c.metadata, timeout=timeout)


def header(name: str, capture: int = pb2.CAPTURE_AUTO, size: int | None = None) -> Any:
    h = pb2.ImageHeader(name=name, capture=capture)
    if size is not None:
        h.size = size
    return h


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


# -- end to end -----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def run(
    dep: GrpcDeployment, a: GrpcClient, scene: Path, tmp_path_factory: pytest.TempPathFactory
) -> dict[str, Any]:
    """The whole flow once over gRPC; the tests below check its parts."""
    t: dict[str, float] = {}
    t0 = time.perf_counter()
    p = a.create_project("grpc-e2e")
    paths = sorted((scene / "images").iterdir())
    # 64 KiB chunks: every image arrives in several pieces; capture auto: the DJI XMP decides
    uploaded = a.upload(p.id, [ImageSource.of(x) for x in paths], chunk_size=64 * 1024)
    t["upload"] = time.perf_counter() - t0

    t1 = time.perf_counter()
    accepted = a.submit_matching(
        p.id, pair_list=PAIRS, resize=RESIZE, method=METHOD, reconstruct=True, mapper="incremental"
    )
    match_events = list(a.watch_job(accepted.job.id, timeout=1200))
    t["match"] = time.perf_counter() - t1
    t2 = time.perf_counter()
    recon_events = list(a.watch_job(accepted.reconstruct_job.id, timeout=600))
    t["reconstruct"] = time.perf_counter() - t2

    t3 = time.perf_counter()
    out = tmp_path_factory.mktemp("grpc-model")
    info, zpath = a.download_model(p.id, out / "model.zip")
    zipfile.ZipFile(zpath).extractall(out)
    t["download"] = time.perf_counter() - t3
    t["total"] = time.perf_counter() - t0
    return {
        "pid": p.id,
        "paths": paths,
        "uploaded": uploaded,
        "accepted": accepted,
        "match_events": match_events,
        "recon_events": recon_events,
        "info": info,
        "zip": zpath,
        "out": out,
        "timings": t,
    }


def test_e2e_timings(run: dict[str, Any], dep: GrpcDeployment, capsys: pytest.CaptureFixture[str]) -> None:
    t = run["timings"]
    with capsys.disabled():
        print(
            f"\n[grpc e2e] 6 images, {run['match_events'][-1].progress.total} pairs, {METHOD} at {RESIZE}px: "
            + ", ".join(f"{k} {v:.1f}s" for k, v in t.items())
        )
    assert run["match_events"][-1].state == pb2.JOB_STATE_SUCCEEDED, (run["match_events"][-1], dep.logs())
    assert run["recon_events"][-1].state == pb2.JOB_STATE_SUCCEEDED, (run["recon_events"][-1], dep.logs())


def test_streamed_upload_stored_every_byte(run: dict[str, Any], a: GrpcClient, dep: GrpcDeployment) -> None:
    up = run["uploaded"]
    assert [i.name for i in up] == [p.name for p in run["paths"]]
    for img, path in zip(up, run["paths"], strict=True):
        assert img.created and img.capture == pb2.CAPTURE_AUTO
        assert img.sha256 == sha256(path) and img.size_bytes == path.stat().st_size
        assert (img.width, img.height, img.format) == (640, 480, "png")
        stored = dep.home / "projects" / run["pid"] / "images" / path.name
        assert stored.read_bytes() == path.read_bytes()
    # the same bytes again: the same images, nothing new
    again = a.upload(run["pid"], [ImageSource.of(p) for p in run["paths"][:2]])
    assert [(i.id, i.created) for i in again] == [(i.id, False) for i in up[:2]]


def test_watch_job_streams_progress_to_the_end(run: dict[str, Any]) -> None:
    events = run["match_events"]
    seen = [(e.state, e.progress.done, e.progress.total) for e in events]
    running = [(d, n) for s, d, n in seen if s == pb2.JOB_STATE_RUNNING and n]
    assert running and running[0][0] == 0, seen  # at 0 of the total once planned
    dones = [d for d, _ in running]
    assert dones == sorted(dones) and len(set(dones)) >= 3, seen  # moves up, step by step
    assert seen[-1] == (pb2.JOB_STATE_SUCCEEDED, len(PAIRS), len(PAIRS)), seen
    assert all(s != pb2.JOB_STATE_SUCCEEDED for s, _, _ in seen[:-1])  # the stream ends with the end
    recon = run["recon_events"]
    assert recon[0].kind == pb2.JOB_KIND_RECONSTRUCT and recon[0].after_job_id == events[-1].id
    assert recon[-1].state == pb2.JOB_STATE_SUCCEEDED and recon[-1].finished_at.seconds > 0
    assert to_dict(events[-1].options)["resize"] == RESIZE


def test_model_download_registers_every_image(run: dict[str, Any]) -> None:
    out, info = run["out"], run["info"]
    assert info.format == pb2.MODEL_FORMAT_ZIP and info.size == run["zip"].stat().st_size
    assert info.sha256 == sha256(run["zip"])  # the client checked it too
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert (out / "sparse" / "0" / "images.txt").is_file() and (out / "points.ply").is_file()
    summary = json.loads((out / "summary.json").read_text())
    assert rec.num_reg_images() == summary["registered"] == summary["images"] == 6, summary
    assert info.summary.registered == 6 and info.summary.images == 6
    assert info.summary.points3d == rec.num_points3D() == summary["points3D"] > 0
    assert info.summary.mean_track_length == pytest.approx(summary["mean_track_length"])
    assert to_dict(info.summary.full) == to_dict(run["recon_events"][-1].result)


def test_model_formats_and_project(run: dict[str, Any], a: GrpcClient, tmp_path: Path) -> None:
    info, path = a.download_model(run["pid"], tmp_path / "summary.json", "json")
    assert json.loads(path.read_text())["points3D"] == info.summary.points3d
    info, path = a.download_model(run["pid"], tmp_path / "points.ply", "ply")
    assert path.read_bytes() == (run["out"] / "points.ply").read_bytes()
    assert f"element vertex {info.summary.points3d}".encode() in path.read_bytes()[:300]
    p = a.get_project(run["pid"])
    assert p.has_model and p.images == 6 and p.name == "grpc-e2e"
    assert run["pid"] in [q.id for q in a.list_projects()]


def test_model_exports_stream_the_cached_zips(
    run: dict[str, Any], a: GrpcClient, dep: GrpcDeployment, tmp_path: Path
) -> None:
    """GetModel's export formats: the zip the service keeps beside the model (built by the first
    request), its summary in ``info``; tests/test_export.py checks the formats themselves."""
    formats = {
        "nerfstudio": (pb2.MODEL_FORMAT_NERFSTUDIO, "transforms.json"),
        "colmap-text": (pb2.MODEL_FORMAT_COLMAP_TEXT, "images.txt"),
        "hloc": (pb2.MODEL_FORMAT_HLOC, "matches.h5"),
        "openmvs": (pb2.MODEL_FORMAT_OPENMVS, "sparse/cameras.bin"),
    }
    exports = dep.home / "projects" / run["pid"] / "model" / "exports"
    for fmt, (enum, inside) in formats.items():
        info, path = a.download_model(run["pid"], tmp_path / f"{fmt}.zip", fmt, timeout=600)
        assert info.format == enum and info.file_name == f"{run['pid']}-{fmt}.zip"
        assert info.summary.registered == 6 and info.summary.points3d == run["info"].summary.points3d
        assert info.size == path.stat().st_size and info.sha256 == sha256(path)
        with zipfile.ZipFile(path) as z:
            assert inside in z.namelist() and json.loads(z.read("summary.json"))["registered"] == 6
        cached = list(exports.glob(f"*/{fmt}.zip"))
        assert len(cached) == 1 and cached[0].read_bytes() == path.read_bytes()
    with zipfile.ZipFile(tmp_path / "nerfstudio.zip") as z:
        frames = json.loads(z.read("transforms.json"))["frames"]
    assert sorted(f["file_path"] for f in frames) == sorted(f"images/{p.name}" for p in run["paths"])


def test_capture_resolved_from_xmp(run: dict[str, Any], a: GrpcClient) -> None:
    images = a.list_images(run["pid"])
    assert {i.name: i.aerial for i in images} == {p.name: p.name.startswith("aerial") for p in run["paths"]}
    assert all(i.HasField("aerial") for i in images)


def test_matching_again_matches_nothing_new_and_reconstruction(run: dict[str, Any], a: GrpcClient) -> None:
    job = a.submit_matching(run["pid"], pair_list=PAIRS, resize=RESIZE, method=METHOD).job
    last = list(a.watch_job(job.id, timeout=120))[-1]
    assert last.state == pb2.JOB_STATE_SUCCEEDED and (last.progress.done, last.progress.total) == (0, 0)
    recon = a.submit_reconstruction(run["pid"], mapper="incremental")
    assert recon.kind == pb2.JOB_KIND_RECONSTRUCT and recon.state == pb2.JOB_STATE_QUEUED
    done = list(a.watch_job(recon.id, timeout=600))[-1]
    assert done.state == pb2.JOB_STATE_SUCCEEDED and to_dict(done.result)["registered"] == 6


# -- MatchPair ------------------------------------------------------------------------------------
def gt_fundamental(scene: Path, name0: str, name1: str) -> np.ndarray:
    """x1^T F x0 = 0 for OpenCV pixel coordinates, from the scene's ground-truth poses."""
    gt = pycolmap.Reconstruction(str(scene / "gt"))
    ims = {im.name: im for im in gt.images.values()}
    (i0, i1) = ims[name0], ims[name1]
    T0, T1 = i0.cam_from_world(), i1.cam_from_world()
    R0, t0 = T0.rotation.matrix(), np.asarray(T0.translation)
    R1, t1 = T1.rotation.matrix(), np.asarray(T1.translation)
    R, t = R1 @ R0.T, t1 - R1 @ R0.T @ t0
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    shift = np.array([[1, 0, 0.5], [0, 1, 0.5], [0, 0, 1]])  # COLMAP's pixel centres are at +0.5
    K0 = gt.cameras[i0.camera_id].calibration_matrix() @ np.eye(3)
    K1 = gt.cameras[i1.camera_id].calibration_matrix() @ np.eye(3)
    return shift.T @ np.linalg.inv(K1).T @ tx @ R @ np.linalg.inv(K0) @ shift


def epipolar_px(F: np.ndarray, k0: np.ndarray, k1: np.ndarray) -> np.ndarray:
    """Distance of each point in image 1 from its epipolar line."""
    h0 = np.c_[k0, np.ones(len(k0))]
    h1 = np.c_[k1, np.ones(len(k1))]
    lines = h0 @ F.T
    return np.abs(np.sum(lines * h1, 1)) / np.linalg.norm(lines[:, :2], axis=1)


def test_match_pair_runs_on_the_worker(
    run: dict[str, Any], a: GrpcClient, dep: GrpcDeployment, scene: Path
) -> None:
    img = scene / "images"
    r = a.match_pair(
        ImageSource.of(img / "ground_00.png"), ImageSource.of(img / "ground_01.png"), resize=PAIR_RESIZE
    )
    assert r.method == "auto" and not r.tiled and r.sizes == ((640, 480), (640, 480))
    assert len(r) > 100 and r.keypoints0.shape == r.keypoints1.shape == (len(r), 2)
    err = epipolar_px(gt_fundamental(scene, "ground_00.png", "ground_01.png"), r.keypoints0, r.keypoints1)
    assert np.median(err) < 2 and np.mean(err < 5) > 0.8, np.percentile(err, [50, 90])
    own = epipolar_px(r.F, r.keypoints0, r.keypoints1)  # the F sent back fits the matches sent back
    assert np.median(own) < 1.0
    assert r.timings["total"] > 0
    # an aerial image said to be aerial is matched as five crops against the ground image (the e2e
    # run left the crops' features on disk)
    t = a.match_pair(
        ImageSource.of(img / "aerial_00.png", "aerial"),
        ImageSource.of(img / "ground_00.png", "ground"),
        method=METHOD,
        resize=RESIZE,
    )
    assert t.tiled and t.method == METHOD and len(t) > 20
    assert dep.wait_unstaged() == []  # nothing kept
    # the server process matched nothing itself: torch was never loaded there
    assert dep.server is not None
    maps = Path(f"/proc/{dep.server.pid}/maps").read_text()
    assert "libtorch" not in maps, "the gRPC server loaded torch"
    assert "match_two" in "".join(p.read_text() for p in dep.root.glob("worker-*.log"))


def test_match_pair_honours_the_deadline(a: GrpcClient, dep: GrpcDeployment, scene: Path) -> None:
    img = scene / "images"
    t0 = time.monotonic()
    code = code_of(
        lambda: a.match_pair(
            ImageSource.of(img / "aerial_01.png"),
            ImageSource.of(img / "ground_03.png"),
            resize=640,
            timeout=0.5,
        )
    )
    assert code == grpc.StatusCode.DEADLINE_EXCEEDED and time.monotonic() - t0 < 5
    assert dep.wait_unstaged() == []


@pytest.mark.parametrize(
    ("case", "status", "message"),
    [
        ("one image", grpc.StatusCode.INVALID_ARGUMENT, "1 were sent"),
        ("three images", grpc.StatusCode.INVALID_ARGUMENT, "a third was sent"),
        ("not an image", grpc.StatusCode.INVALID_ARGUMENT, "not a readable image"),
        ("bad option", grpc.StatusCode.INVALID_ARGUMENT, "resize"),
        ("pairs option", grpc.StatusCode.INVALID_ARGUMENT, "method must be one of"),
        ("options late", grpc.StatusCode.INVALID_ARGUMENT, "expected an image header"),
        ("no key", grpc.StatusCode.UNAUTHENTICATED, "key"),
    ],
)
def test_bad_match_pair(
    a: GrpcClient, dep: GrpcDeployment, scene: Path, case: str, status: grpc.StatusCode, message: str
) -> None:
    png = (scene / "images" / "ground_00.png").read_bytes()

    def image(name: str, data: bytes) -> list[Any]:
        return [pb2.MatchPairRequest(image=header(name)), pb2.MatchPairRequest(chunk=data)]

    opts: list[Any] = []
    images = image("a.png", png) + image("b.png", png)
    metadata = a.metadata
    if case == "one image":
        images = image("a.png", png)
    elif case == "three images":
        images += image("c.png", png)
    elif case == "not an image":
        images = image("a.png", png) + image("b.png", b"GIF89a but not really")
    elif case == "bad option":
        opts = [pb2.MatchPairRequest(options=pb2.MatchPairOptions(resize=5))]
    elif case == "pairs option":
        opts = [pb2.MatchPairRequest(options=pb2.MatchPairOptions(method="magic"))]
    elif case == "options late":
        images = [*image("a.png", png), pb2.MatchPairRequest(options=pb2.MatchPairOptions())]
    elif case == "no key":
        metadata = ()
    code, details = error_of(lambda: a.stub.MatchPair(iter(opts + images), metadata=metadata, timeout=60))
    assert code == status and message in details, (case, code, details)
    assert dep.wait_unstaged() == []


# -- health, reflection, auth ------------------------------------------------------------------------
def test_health_checking(dep: GrpcDeployment) -> None:
    with grpc.insecure_channel(dep.target) as ch:  # no key needed
        stub = health_pb2_grpc.HealthStub(ch)
        for name in ("", "geomatch.v1.Matching"):
            assert stub.Check(health_pb2.HealthCheckRequest(service=name), timeout=5).status == 1  # SERVING
        code = code_of(
            lambda: stub.Check(health_pb2.HealthCheckRequest(service="nope.v1.Nothing"), timeout=5)
        )
        assert code == grpc.StatusCode.NOT_FOUND
        watch = stub.Watch(health_pb2.HealthCheckRequest(service="geomatch.v1.Matching"), timeout=5)
        assert next(watch).status == health_pb2.HealthCheckResponse.SERVING
        watch.cancel()


def test_reflection_lets_a_client_without_generated_code_call(dep: GrpcDeployment, key: str) -> None:
    """What grpcurl does: discover the service, build its messages from the served descriptors."""
    from google.protobuf import descriptor_pool, message_factory

    with grpc.insecure_channel(dep.target) as ch:
        db = ProtoReflectionDescriptorDatabase(ch)
        services = set(db.get_services())
        assert {"geomatch.v1.Matching", "grpc.health.v1.Health"} <= services
        pool = descriptor_pool.DescriptorPool(db)
        svc = pool.FindServiceByName("geomatch.v1.Matching")
        assert {m.name for m in svc.methods} == SERVED_METHODS
        upload = svc.methods_by_name["UploadImages"]
        assert upload.client_streaming and not upload.server_streaming
        assert svc.methods_by_name["WatchJob"].server_streaming
        req_cls = message_factory.GetMessageClass(
            pool.FindMessageTypeByName("geomatch.v1.CreateProjectRequest")
        )
        resp_cls = message_factory.GetMessageClass(pool.FindMessageTypeByName("geomatch.v1.Project"))
        create = ch.unary_unary(
            "/geomatch.v1.Matching/CreateProject",
            request_serializer=req_cls.SerializeToString,
            response_deserializer=resp_cls.FromString,
        )
        p = create(req_cls(name="via reflection"), metadata=(("authorization", f"Bearer {key}"),), timeout=10)
        assert len(p.id) == 32 and p.name == "via reflection"


@pytest.mark.parametrize(
    "metadata", [(), (("authorization", "Bearer gm_not-a-key"),), (("authorization", "Basic x"),)]
)
def test_calls_without_a_valid_key_are_unauthenticated(
    a: GrpcClient, project: str, dep: GrpcDeployment, scene: Path, metadata: tuple[tuple[str, str], ...]
) -> None:
    before = dep.project_state(project)
    s = a.stub
    calls = [
        lambda: s.ListProjects(pb2.ListProjectsRequest(), metadata=metadata, timeout=10),
        lambda: s.GetProject(pb2.GetProjectRequest(project_id=project), metadata=metadata, timeout=10),
        lambda: list(s.WatchJob(pb2.WatchJobRequest(job_id=project), metadata=metadata, timeout=10)),
        lambda: list(s.GetModel(pb2.GetModelRequest(project_id=project), metadata=metadata, timeout=10)),
        lambda: s.UploadImages(
            iter(
                [
                    pb2.UploadImagesRequest(project_id=project, image=header("x.png")),
                    pb2.UploadImagesRequest(chunk=(scene / "images" / "ground_01.png").read_bytes()),
                ]
            ),
            metadata=metadata,
            timeout=10,
        ),
    ]
    for call in calls:
        code, details = error_of(call)
        assert code == grpc.StatusCode.UNAUTHENTICATED and "key" in details
    assert dep.project_state(project) == before


def test_another_tenants_project_and_jobs_are_not_found(
    a: GrpcClient, b: GrpcClient, project: str, dep: GrpcDeployment, scene: Path
) -> None:
    a.upload(project, [ImageSource.of(scene / "images" / "ground_01.png", "ground")])
    job = a.submit_matching(project, resize=256, method="sparse").job
    before = dep.project_state(project)
    assert project not in [p.id for p in b.list_projects()]
    png = (scene / "images" / "ground_02.png").read_bytes()
    for call in [
        lambda: b.get_project(project),
        lambda: b.delete_project(project),
        lambda: b.list_images(project),
        lambda: b.submit_matching(project),
        lambda: b.submit_reconstruction(project),
        lambda: b.download_model(project, dep.root / "stolen.zip"),
        lambda: b.upload(project, [ImageSource("g.png", data=png)]),
        lambda: b.get_job(job.id),
        lambda: list(b.watch_job(job.id, timeout=10)),
        lambda: b.cancel_job(job.id),
    ]:
        code, details = error_of(call)
        assert code == grpc.StatusCode.NOT_FOUND and "not found" in details, details
    assert dep.project_state(project) == before
    assert a.get_job(job.id).state != pb2.JOB_STATE_CANCELLED  # B's cancel did nothing
    a.cancel_job(job.id)  # frees the worker (cancelling itself: test_cancel_job)


# -- bad uploads: the REST list, each with its gRPC status ----------------------------------------------
GRPC_STATUS = {
    "not an image": grpc.StatusCode.INVALID_ARGUMENT,
    "truncated": grpc.StatusCode.INVALID_ARGUMENT,
    "truncated bmp": grpc.StatusCode.INVALID_ARGUMENT,
    "zero bytes": grpc.StatusCode.INVALID_ARGUMENT,
    "decompression bomb": grpc.StatusCode.INVALID_ARGUMENT,
    "over the byte limit": grpc.StatusCode.RESOURCE_EXHAUSTED,
    "unsupported format": grpc.StatusCode.INVALID_ARGUMENT,
    "path separator": grpc.StatusCode.INVALID_ARGUMENT,
    "nested path": grpc.StatusCode.INVALID_ARGUMENT,
    "backslash": grpc.StatusCode.INVALID_ARGUMENT,
    "dot dot": grpc.StatusCode.INVALID_ARGUMENT,
    "dots inside": grpc.StatusCode.INVALID_ARGUMENT,
}


@pytest.mark.parametrize("declare_size", [True, False], ids=["size-declared", "size-unknown"])
@pytest.mark.parametrize("label", sorted(GRPC_STATUS))
def test_bad_upload_is_refused_and_nothing_stored(
    a: GrpcClient, dep: GrpcDeployment, project: str, scene: Path, label: str, declare_size: bool
) -> None:
    cases = {c[0]: c for c in bad_files(scene)}
    assert sorted(cases) == sorted(GRPC_STATUS)  # a new bad input of the REST tests needs its status here
    _, name, data, _, message = cases[label]
    good = (scene / "images" / "ground_03.png").read_bytes()
    before = dep.project_state(project)
    messages = [
        pb2.UploadImagesRequest(
            project_id=project, image=header("good.png", size=len(good) if declare_size else None)
        )
    ]
    messages += [pb2.UploadImagesRequest(chunk=good[i : i + MiB]) for i in range(0, len(good), MiB)]
    messages.append(pb2.UploadImagesRequest(image=header(name, size=len(data) if declare_size else None)))
    messages += [pb2.UploadImagesRequest(chunk=data[i : i + MiB]) for i in range(0, len(data), MiB)]
    code, details = error_of(lambda: raw_upload(a, messages))
    assert code == GRPC_STATUS[label] and message in details, (label, code, details)
    assert dep.wait_unstaged() == [] and dep.project_state(project) == before, label


def test_framing_violations(a: GrpcClient, dep: GrpcDeployment, project: str, scene: Path) -> None:
    png = (scene / "images" / "ground_02.png").read_bytes()
    U = pb2.UploadImagesRequest
    before = dep.project_state(project)
    inv, big, nf = (
        grpc.StatusCode.INVALID_ARGUMENT,
        grpc.StatusCode.RESOURCE_EXHAUSTED,
        grpc.StatusCode.NOT_FOUND,
    )
    start = U(project_id=project, image=header("a.png"))
    cases: list[tuple[list[Any], grpc.StatusCode, str]] = [
        ([start, U(chunk=b"x" * (MiB + 1))], big, "at most"),  # over 1 MiB: refused by the server
        ([start, U(chunk=b"x" * (5 * MiB))], big, ""),  # over gRPC's 4 MiB message limit
        ([U(project_id=project, image=header("a.png", size=3 * MiB))], big, "declared"),
        ([U(project_id=project, image=header("a.png", size=len(png) + 1)), U(chunk=png)], inv, "declared"),
        ([U(project_id=project, image=header("a.png", size=10)), U(chunk=png)], inv, "declared"),
        ([U(project_id=project, chunk=png)], inv, "expected an image header"),
        ([U(image=header("a.png")), U(chunk=png)], inv, "project_id"),
        ([U(project_id=project)], inv, "no images"),
        ([], inv, "project_id"),
        ([U(project_id=project, image=header("a.png", capture=7)), U(chunk=png)], inv, "capture"),
        ([start, U(chunk=png), U(project_id="f" * 32, image=header("b.png"))], inv, "project_id changed"),
        ([start, U(chunk=png), U(image=header("a.png")), U(chunk=png)], inv, "sent twice"),
        ([U(project_id="0" * 32, image=header("a.png")), U(chunk=png)], nf, "not found"),
    ]
    for messages, status, message in cases:
        code, details = error_of(lambda m=messages: raw_upload(a, m))
        assert code == status and message in details, (messages[:1], code, details)
    # a message that is not a protobuf of the method's type, in the stream and as a unary request
    raw = a.channel.stream_unary(
        "/geomatch.v1.Matching/UploadImages",
        request_serializer=lambda b: b,
        response_deserializer=lambda b: b,
    )
    first = U(project_id=project, image=header("a.png")).SerializeToString()
    code, details = error_of(lambda: raw(iter([first, b"\xff\xff\xff\xff"]), metadata=a.metadata, timeout=10))
    assert code == grpc.StatusCode.INVALID_ARGUMENT and "malformed request" in details
    unary = a.channel.unary_unary(
        "/geomatch.v1.Matching/CreateProject",
        request_serializer=lambda b: b,
        response_deserializer=lambda b: b,
    )
    code, details = error_of(lambda: unary(b"\x0a\xff", metadata=a.metadata, timeout=10))
    assert code == grpc.StatusCode.INVALID_ARGUMENT and "malformed request" in details
    assert dep.wait_unstaged() == [] and dep.project_state(project) == before


# -- bad requests -----------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"pair_list": [("ground_00.png", "nope.png")]}, "not an image of this project"),
        ({"pair_list": [("ground_00.png", "ground_00.png")]}, "itself"),
        ({"pair_list": []}, "empty"),
        ({"pair_spec": "nearest:3"}, "bad pairs"),
        ({"pair_spec": "sequential:0"}, "bad pairs"),
        ({"method": "magic"}, "method must be one of"),
        ({"resize": 5}, "resize"),
        ({"tiling": "sometimes"}, "tiling"),
        ({"reconstruct": True, "mapper": "hierarchical"}, "mapper"),
        ({"snap_radius": 99.0}, "snap_radius"),
    ],
)
def test_bad_match_request_is_invalid_and_starts_nothing(
    a: GrpcClient, dep: GrpcDeployment, project: str, options: dict[str, Any], message: str
) -> None:
    before = dep.project_state(project)
    code, details = error_of(lambda: a.submit_matching(project, **options))
    assert code == grpc.StatusCode.INVALID_ARGUMENT and message in details, details
    assert dep.project_state(project) == before


def test_bad_requests(a: GrpcClient, dep: GrpcDeployment, scene: Path) -> None:
    missing = "0123456789abcdef0123456789abcdef"
    for call in [
        lambda: a.get_project(missing),
        lambda: a.get_project("not-an-id"),
        lambda: a.delete_project(missing),
        lambda: a.list_images(missing),
        lambda: a.submit_matching(missing),
        lambda: a.submit_reconstruction(missing),
        lambda: a.get_job(missing),
        lambda: a.cancel_job(missing),
        lambda: list(a.watch_job(missing, timeout=10)),
        lambda: a.download_model(missing, dep.root / "x.zip"),
    ]:
        code, details = error_of(call)
        assert code == grpc.StatusCode.NOT_FOUND and "not found" in details, details
    for name in ("", " " * 3, "x" * 201):
        assert code_of(lambda n=name: a.create_project(n)) == grpc.StatusCode.INVALID_ARGUMENT
    code, details = error_of(lambda: a.create_project("x", method="nope"))
    assert code == grpc.StatusCode.INVALID_ARGUMENT and "method" in details
    p = a.create_project("x", pairs="sequential:3", resize=320)
    assert p.config.pairs == "sequential:3" and p.config.resize == 320 and not p.config.HasField("method")
    # fewer than 2 images, nothing to reconstruct, no model
    lonely = a.create_project("lonely").id
    code, details = error_of(lambda: a.submit_matching(lonely))
    assert code == grpc.StatusCode.INVALID_ARGUMENT and "has 0 image(s)" in details
    a.upload(lonely, [ImageSource.of(scene / "images" / "ground_00.png")])
    code, details = error_of(lambda: a.submit_matching(lonely))
    assert code == grpc.StatusCode.INVALID_ARGUMENT and "matching needs at least 2" in details
    assert code_of(lambda: a.submit_reconstruction(lonely)) == grpc.StatusCode.FAILED_PRECONDITION
    code, details = error_of(lambda: a.submit_reconstruction(lonely, min_pose_inliers=2))
    assert code == grpc.StatusCode.INVALID_ARGUMENT and "min_pose_inliers must be 0 (auto" in details
    code, details = error_of(lambda: a.download_model(lonely, dep.root / "x.zip"))
    assert code == grpc.StatusCode.NOT_FOUND and "no model yet" in details
    code, details = error_of(lambda: a.download_model(lonely, dep.root / "x.zip", "hloc"))
    assert code == grpc.StatusCode.NOT_FOUND and "no model yet" in details
    assert dep.project_state(lonely)[1] == 0
    # the same name with other bytes
    other = ImageSource("ground_00.png", data=(scene / "images" / "aerial_00.png").read_bytes())
    code, details = error_of(lambda: a.upload(lonely, [other]))
    assert code == grpc.StatusCode.FAILED_PRECONDITION and "other content" in details
    a.delete_project(lonely)
    assert code_of(lambda: a.get_project(lonely)) == grpc.StatusCode.NOT_FOUND
    assert not (dep.home / "projects" / lonely).exists()


def test_cancel_job(a: GrpcClient, scene: Path) -> None:
    p = a.create_project("cancel", resize=480).id
    # the whole scene: its eight aerial x ground pairs are tiled, matched crop by crop, so the job
    # outlasts the watch below many times over (a few ground photos can finish within it)
    a.upload(p, [ImageSource.of(f) for f in sorted((scene / "images").iterdir())])
    job = a.submit_matching(p).job
    watch = a.watch_job(job.id, timeout=120)
    assert next(watch).id == job.id
    # a watch's deadline ends it, and the job goes on
    t0 = time.monotonic()
    assert code_of(lambda: list(a.watch_job(job.id, timeout=1.0))) == grpc.StatusCode.DEADLINE_EXCEEDED
    assert time.monotonic() - t0 < 5 and a.get_job(job.id).state in (
        pb2.JOB_STATE_QUEUED,
        pb2.JOB_STATE_RUNNING,
    )
    cancelled = a.cancel_job(job.id)
    assert cancelled.state == pb2.JOB_STATE_CANCELLED and "cancelled" in cancelled.error
    assert list(watch)[-1].state == pb2.JOB_STATE_CANCELLED  # the open stream ends with it
    assert a.cancel_job(job.id).state == pb2.JOB_STATE_CANCELLED  # idempotent


# -- disconnects and concurrency -------------------------------------------------------------------
def test_client_cancelling_mid_upload_leaves_nothing(
    a: GrpcClient, dep: GrpcDeployment, project: str, scene: Path
) -> None:
    before = dep.project_state(project)
    png = (scene / "images" / "aerial_01.png").read_bytes()
    sent_half = threading.Event()
    release = threading.Event()

    def messages() -> Iterator[Any]:
        yield pb2.UploadImagesRequest(project_id=project, image=header("first.png"))
        yield pb2.UploadImagesRequest(chunk=(scene / "images" / "ground_02.png").read_bytes())
        yield pb2.UploadImagesRequest(image=header("second.png", size=len(png)))
        yield pb2.UploadImagesRequest(chunk=png[: len(png) // 2])
        sent_half.set()
        release.wait(30)

    call = a.stub.UploadImages.future(messages(), metadata=a.metadata, timeout=60)
    assert sent_half.wait(30)
    deadline = time.monotonic() + 30  # the server is mid-image: the second image is being staged
    while len(dep.staged()) < 2 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert len(dep.staged()) == 2, dep.staged()
    assert call.cancel() and call.code() == grpc.StatusCode.CANCELLED
    release.set()
    assert dep.wait_unstaged() == [] and dep.project_state(project) == before


def test_upload_past_its_deadline_leaves_nothing(
    a: GrpcClient, dep: GrpcDeployment, project: str, scene: Path
) -> None:
    before = dep.project_state(project)
    png = (scene / "images" / "aerial_01.png").read_bytes()
    stop = threading.Event()

    def messages() -> Iterator[Any]:
        yield pb2.UploadImagesRequest(project_id=project, image=header("late.png", size=len(png)))
        yield pb2.UploadImagesRequest(chunk=png[:1000])
        stop.wait(10)  # the rest never comes in time

    try:
        code = code_of(lambda: a.stub.UploadImages(messages(), metadata=a.metadata, timeout=1.0))
    finally:
        stop.set()
    assert code == grpc.StatusCode.DEADLINE_EXCEEDED
    assert dep.wait_unstaged() == [] and dep.project_state(project) == before


CLIENT = """
import sys, threading
from service.grpcapi.pb import pb2
from service.clients.grpc_client import GrpcClient
target, key, project, path = sys.argv[1:]
data = open(path, "rb").read()
def messages():
    header = pb2.ImageHeader(name="killed.png", size=len(data))
    yield pb2.UploadImagesRequest(project_id=project, image=header)
    yield pb2.UploadImagesRequest(chunk=data[: len(data) // 2])
    print("half", flush=True)
    threading.Event().wait()
c = GrpcClient(target, key)
c.stub.UploadImages(messages(), metadata=c.metadata)
"""


def test_killed_client_mid_upload_leaves_nothing(
    key: str, dep: GrpcDeployment, project: str, scene: Path
) -> None:
    before = dep.project_state(project)
    proc = subprocess.Popen(
        [sys.executable, "-c", CLIENT, dep.target, key, project, str(scene / "images" / "aerial_00.png")],
        stdout=subprocess.PIPE,
        text=True,
        cwd=Path(__file__).resolve().parents[2],
        env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])},
    )
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "half"
        deadline = time.monotonic() + 30
        while not dep.staged() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert dep.staged(), "the server never started staging the image"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    assert dep.wait_unstaged() == [] and dep.project_state(project) == before


def test_two_clients_upload_to_one_project_at_once(dep: GrpcDeployment, key: str, scene: Path) -> None:
    """Two streams open at the same time, their images interleaved, one image sent by both."""
    with dep.grpc_client(key) as setup:
        pid = setup.create_project("together").id
    names = sorted(p.name for p in (scene / "images").iterdir())
    shared = names[0]
    halves = {0: [shared, *names[1:3]], 1: [shared, *names[3:6]]}
    both_open = threading.Barrier(2, timeout=30)
    results: dict[int, Any] = {}

    def client(i: int) -> None:
        def messages(together: bool) -> Iterator[Any]:
            for j, name in enumerate(halves[i]):
                data = (scene / "images" / name).read_bytes()
                yield pb2.UploadImagesRequest(
                    project_id=pid if j == 0 else "", image=header(name, size=len(data))
                )
                yield pb2.UploadImagesRequest(chunk=data[: len(data) // 2])
                if j == 0 and together:
                    both_open.wait()  # neither stream has finished an image before both started
                yield pb2.UploadImagesRequest(chunk=data[len(data) // 2 :])

        with dep.grpc_client(key) as c:
            for attempt in range(3):  # the shared image may be committed by both in one instant: retry
                try:
                    reply = c.stub.UploadImages(messages(attempt == 0), metadata=c.metadata, timeout=60)
                    results[i] = list(reply.images)
                    return
                except grpc.RpcError as e:
                    results[i] = e
                    if e.code() != grpc.StatusCode.FAILED_PRECONDITION or "concurrently" not in (
                        e.details() or ""
                    ):
                        return

    threads = [threading.Thread(target=client, args=(i,)) for i in (0, 1)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(90)
    for i in (0, 1):
        assert isinstance(results[i], list), results[i]
        assert [im.name for im in results[i]] == halves[i]
    ids = {im.name: im.id for i in (0, 1) for im in results[i]}
    assert results[0][0].id == results[1][0].id  # the shared image is one image
    assert sum(im.created for i in (0, 1) for im in results[i]) == 6
    assert dep.project_state(pid) == (names, 0, [])
    assert sorted(ids) == names


def test_over_rest_and_grpc_the_bytes_agree(run: dict[str, Any], dep: GrpcDeployment, a: GrpcClient) -> None:
    """The same use cases: what gRPC stored is what the metadata store and the disk hold."""
    rows = dep.metadata(
        "SELECT name, sha256, capture FROM images WHERE project_id = ? ORDER BY name", run["pid"]
    )
    assert rows == [(p.name, sha256(p), "auto") for p in run["paths"]]
    z = zipfile.ZipFile(io.BytesIO(run["zip"].read_bytes()))
    assert "summary.json" in z.namelist() and any(n.startswith("sparse/0/") for n in z.namelist())
