"""gRPC in the embedded default: ``geomatch serve`` runs HTTP and gRPC over one Service (one job
runner, one configuration), MatchPair runs on that process's runner, ``geomatch submit`` (over
gRPC and over HTTP) drives a whole batch; ports, and the generated code's build step and its errors."""

from __future__ import annotations

import contextlib
import json
import re
import socket
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path

import grpc
import pytest

from service.clients.grpc_client import GrpcClient, ImageSource
from service.grpcapi import codegen

from .grpc_harness import GrpcDeployment, running_grpc
from .harness import GEOMATCH, free_port, upload

ROOT = Path(__file__).resolve().parents[2]
GROUND = ["ground_00.png", "ground_01.png", "ground_02.png", "ground_03.png"]
# the four ground images register at this, every one right (measured); at 320 px ground_00's only
# right pair shares no triangulated point and the view-graph check drops one of its wrong ones
SUBMIT = ("sparse", 480)


@pytest.fixture(scope="module")
def both(tmp_path_factory: pytest.TempPathFactory) -> Iterator[GrpcDeployment]:
    with running_grpc(tmp_path_factory.mktemp("grpc-embedded"), None, "serve") as d:
        yield d


@pytest.fixture(scope="module")
def key(both: GrpcDeployment) -> str:
    m = re.search(r"API key \(tenant 'local'\): (gm_\S+)", both.server_out)
    assert m, both.server_out
    return m.group(1)


@pytest.mark.service
def test_serve_runs_http_and_grpc_over_one_service(both: GrpcDeployment, key: str, scene: Path) -> None:
    assert f"gRPC (geomatch.v1.Matching) on {both.target}" in both.server_out
    with both.grpc_client(key) as g, both.client(key) as h:
        pid = g.create_project("both ways", resize=320).id
        assert h.get(f"/v1/projects/{pid}").json()["config"] == {"resize": 320}
        assert upload(h, pid, [scene / "images" / "ground_00.png"], "ground").status_code == 201
        g.upload(pid, [ImageSource.of(scene / "images" / "ground_01.png", "aerial")])
        assert {(i.name, i.capture) for i in g.list_images(pid)} == {
            ("ground_00.png", 3),
            ("ground_01.png", 2),
        }
        assert [i["name"] for i in h.get(f"/v1/projects/{pid}/images").json()["images"]] == [
            "ground_00.png",
            "ground_01.png",
        ]
        g.delete_project(pid)
        assert h.get(f"/v1/projects/{pid}").status_code == 404
        assert h.get("/readyz").json()["checks"]["mode"] == "embedded"


@pytest.mark.service
def test_match_pair_on_the_embedded_runner(both: GrpcDeployment, key: str, scene: Path) -> None:
    """Matched as test_submit matches: its batches then find these features on disk."""
    method, resize = SUBMIT
    with both.grpc_client(key) as g:
        img = scene / "images"
        r = g.match_pair(ImageSource.of(img / GROUND[1]), ImageSource.of(img / GROUND[2]), method, resize)
        assert r.method == method and not r.tiled and len(r) > 30, len(r)
        for k in (r.keypoints0, r.keypoints1):
            assert (k >= -0.5).all() and (k < [639.5, 479.5]).all()
    assert both.wait_unstaged() == []


def geomatch(args: list[str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*GEOMATCH, *args], capture_output=True, text=True, timeout=600)


@pytest.mark.service
@pytest.mark.parametrize("transport", ["grpc", "http"])
def test_submit(both: GrpcDeployment, key: str, scene: Path, tmp_path: Path, transport: str) -> None:
    """`geomatch submit [--grpc] --out`: upload, match, reconstruct, wait, unpack the model; the one
    flow (service.clients.submit) through each client, with the same lines and exit codes."""
    folder = tmp_path / "batch"
    folder.mkdir()
    for n in GROUND:
        (folder / n).write_bytes((scene / "images" / n).read_bytes())
    out = tmp_path / "model"
    if transport == "grpc":
        server, where = ["--grpc", "--grpc-server", both.target], f"{both.target} (gRPC)"
    else:
        server, where = ["--server", both.url], both.url
    args = ["submit", str(folder), *server, "--key", key]
    args += ["--aerial", "aerial_*", "--method", SUBMIT[0], "--resize", str(SUBMIT[1])]
    r = geomatch([*args, "--out", str(out), "--no-progress"])
    assert r.returncode == 0, r.stderr + both.logs()
    assert f"uploading 4 images to {where}\n" in r.stderr, r.stderr
    assert "registered 4/4 images" in r.stdout, r.stdout
    pid = r.stdout.strip().splitlines()[-1]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["images"] == summary["registered"] == 4, summary  # measured: all four register
    assert (out / "sparse" / "0" / "cameras.bin").is_file() and (out / "points.ply").is_file()
    with both.grpc_client(key) as g:
        assert [i.capture for i in g.list_images(pid)] == [3] * 4  # --aerial given: the others are ground

    # without --wait/--out: the jobs are queued, the command says how to follow them and ends
    r = geomatch([*args, "--no-progress"])
    assert r.returncode == 0, r.stderr
    jobs = re.search(r"match job (\S+), then reconstruct job (\S+)", r.stderr)
    assert jobs, r.stderr
    follow, pid = r.stdout.strip().splitlines()
    hint = (
        f"WatchJob {{job_id: {jobs[2]}}} on {both.target}"
        if transport == "grpc"
        else f"{both.url}/v1/jobs/{jobs[2]}/events"
    )
    assert follow.startswith("follow with: ") and follow.endswith(hint), follow
    with both.grpc_client(key) as g:
        for job in (jobs[2], jobs[1]):
            g.cancel_job(job)

    args[args.index(key)] = "gm_wrong"
    bad = geomatch([*args])
    assert bad.returncode == 2 and ("UNAUTHENTICATED" if transport == "grpc" else "HTTP 401") in bad.stderr
    assert bad.stderr.startswith("geomatch: error: "), bad.stderr


@pytest.mark.service
def test_explicit_port_taken_is_an_error(both: GrpcDeployment, tmp_path: Path) -> None:
    port = both.target.rsplit(":", 1)[1]  # held by the running server
    r = subprocess.run(
        [*GEOMATCH, "serve", "--port", str(free_port()), "--grpc-port", port],
        env=GrpcDeployment(tmp_path, None).env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 2 and "cannot listen" in r.stderr, r.stderr


@contextlib.contextmanager
def default_port_taken() -> Iterator[None]:
    """50051 held (by this test, unless something else already holds it)."""
    s = socket.socket()
    try:
        with contextlib.suppress(OSError):
            s.bind(("127.0.0.1", 50051))
            s.listen()
        yield
    finally:
        s.close()


@pytest.mark.service
def test_default_port_taken_serves_http_only_with_a_warning(tmp_path: Path) -> None:
    d = GrpcDeployment(tmp_path, None)
    try:
        with default_port_taken():
            d.start_server()  # geomatch serve with no gRPC option
        assert "gRPC not started" in d.server_out and "--grpc-port" in d.server_out
    finally:
        d.stop()


@pytest.mark.service
def test_grpc_serve_alone_on_a_free_port(tmp_path: Path) -> None:
    d = GrpcDeployment(tmp_path, None)
    try:
        proc = d.spawn(["grpc-serve", "--port", "0"], "server.log")
        d.server = proc
        out, deadline = "", time.monotonic() + 120
        while time.monotonic() < deadline:
            out = (tmp_path / "server.log").read_text()
            if "API key" in out or proc.poll() is not None:
                break
            time.sleep(0.1)
        m = re.search(r"gRPC \(geomatch.v1.Matching\) on (127\.0\.0\.1:(\d+))", out)
        assert m and int(m.group(2)) > 0, out
        key = re.search(r"API key \(tenant 'local'\): (gm_\S+)", out)
        assert key, out
        with GrpcClient(m.group(1), key.group(1)) as g:
            assert g.list_projects() == []
            with pytest.raises(grpc.RpcError) as e:
                GrpcClient(m.group(1), None).list_projects()
            assert e.value.code() == grpc.StatusCode.UNAUTHENTICATED
    finally:
        d.stop()


# -- the generated code ------------------------------------------------------------------------------
@pytest.mark.unit
def test_codegen_writes_importable_modules(tmp_path: Path) -> None:
    written = codegen.generate(out_dir=tmp_path / "gen")
    assert sorted(p.name for p in written) == sorted(codegen.OUTPUTS)
    stub = (tmp_path / "gen" / "geomatch_pb2_grpc.py").read_text()
    assert "from . import geomatch_pb2 as" in stub and "from geomatch.v1" not in stub
    assert (tmp_path / "gen" / codegen.STAMP).read_text().strip() == codegen.proto_digest()
    assert "DO NOT EDIT" in (tmp_path / "gen" / "geomatch_pb2.py").read_text()


def _import_pb(setup: str) -> subprocess.CompletedProcess[str]:
    code = textwrap.dedent(setup) + "\nimport service.grpcapi.pb\n"
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=60)


@pytest.mark.unit
def test_missing_generated_code_says_how_to_make_it() -> None:
    r = _import_pb(
        """
        import sys
        class Block:
            def find_spec(self, name, path=None, target=None):
                if name.startswith("service.grpcapi.geomatch_pb2"):
                    raise ImportError(f"no module named {name}")
        sys.meta_path.insert(0, Block())
        """
    )
    assert r.returncode != 0 and "GeneratedCodeMissing" in r.stderr and "make setup" in r.stderr, r.stderr


@pytest.mark.unit
def test_stale_generated_code_says_how_to_remake_it(tmp_path: Path) -> None:
    proto = tmp_path / "geomatch" / "v1" / "geomatch.proto"
    proto.parent.mkdir(parents=True)
    proto.write_text((codegen.PROTO_ROOT / codegen.PROTO).read_text() + "\n// edited\n")
    r = _import_pb(
        f"""
        from pathlib import Path
        from service.grpcapi import codegen
        codegen.PROTO_ROOT = Path({str(tmp_path)!r})
        """
    )
    assert r.returncode != 0 and "changed since" in r.stderr and "make setup" in r.stderr, r.stderr
