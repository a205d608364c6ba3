"""Pieces of the service without servers: validation rules (and their agreement with the
library), the torch-free import of the API, the on-disk feature store, and job state
transitions on SQLite and PostgreSQL."""

from __future__ import annotations

import re
import struct
import threading
import time
import uuid
import zlib
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from PIL import Image as PILImage
from sqlalchemy import select

from geomatch.features.store import FeatureStore
from geomatch.matching.stored import build_matcher
from geomatch.options import PairSpecError, parse_plan
from geomatch.synth.photos import WarpedPair
from geomatch_core import jobstate
from geomatch_core.errors import BadFile, InvalidRequest, NotFound, too_much_queued
from geomatch_core.models import Job, JobPair, Project, Tenant, new_id
from geomatch_core.store import MetadataStore
from service import ids, validation

from ..loaded_modules import loaded_after
from .test_api import big_bmp_cut_short, bmp_header


@pytest.mark.unit
@pytest.mark.parametrize(
    "spec",
    [
        "exhaustive",
        "sequential:3",
        "retrieval:10",
        " exhaustive ",
        "sequential:0",
        "retrieval",
        "nearest:3",
        "x",
        "",
        "gps:8",
        " gps:8+retrieval:4 ",
        "sequential:2+gps:3+retrieval:1",
        "gps:0",
        "gps:3+gps:4",
        "sequential:1+gps:2+gps:3+retrieval:4",
        "exhaustive+gps:3",
        "gps:3+",
    ],
)
def test_pair_grammar_is_the_librarys(spec: str) -> None:
    """The service, its OpenAPI pattern and the library take the same specs (a repeated kind
    included: schemathesis sends what the pattern allows and expects it accepted)."""
    from service.http.schemas import PAIR_SPEC_PATTERN

    try:
        parse_plan(spec)
        library_ok = True
    except PairSpecError:
        library_ok = False
    try:
        validation.check_option("pairs", spec)
        service_ok = True
    except InvalidRequest:
        service_ok = False
    assert service_ok == library_ok
    assert bool(re.fullmatch(PAIR_SPEC_PATTERN, spec)) == library_ok


@pytest.mark.unit
@pytest.mark.parametrize(
    "name", ["a.jpg", "DJI_0001.JPG", "photo 1.png", "é.png", "a.b.c.tif", "文" * 83 + ".png"]
)
def test_names_accepted(name: str) -> None:
    assert validation.check_name(name) == name


@pytest.mark.unit
@pytest.mark.parametrize(
    "name",
    [
        None,
        "",
        "  ",
        "a/b.jpg",
        "a\\b.jpg",
        "..",
        ".",
        "x/../y.jpg",
        "a..jpg",
        ".hidden.png",
        "a\0.png",
        "x" * 300,
        "文" * 100 + ".jpg",  # 104 characters, 304 bytes: over what a file system takes
        "a\ud800.png",
        "c1\x85.png",
    ],
)
def test_names_refused(name: str | None) -> None:
    with pytest.raises(BadFile):
        validation.check_name(name)


ADAM7 = ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2))


def png(ihdr: bytes, raw: bytes) -> bytes:
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    idat = chunk(b"IDAT", zlib.compress(raw))
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + idat + chunk(b"IEND", b"")


@pytest.mark.unit
def test_ids_the_service_makes_are_known_and_no_other_shape_is() -> None:
    made = new_id()
    assert ids.known_id("project", made) == made
    for bad in ["", "\x00", made[:-1] + "\x00", made.upper(), made + "0", made[:-1], "../" + made[3:]]:
        with pytest.raises(NotFound, match=r"^job "):
            ids.known_id("job", bad)
    with pytest.raises(NotFound) as e:
        ids.known_id("project", "\x00" * 10_000)
    assert len(e.value.message) < 120 and "\\x00" in e.value.message  # escaped, cut short
    assert ids.known_name(made, "a.png") == "a.png"
    for bad in ["a\x00.png", "../a.png", "x" * 201, ""]:
        with pytest.raises(NotFound, match="not found in project"):
            ids.known_name(made, bad)


@pytest.mark.unit
def test_png_check_takes_every_kind_of_png_and_refuses_damage(tmp_path: Path) -> None:
    """The upload check streams a PNG's data instead of decoding it: it must agree with Pillow on
    what a whole PNG is (bit depths, palettes, interlacing) and still find damage."""
    rng = np.random.default_rng(0)
    rgb = (rng.random((37, 29, 3)) * 255).astype(np.uint8)
    path = tmp_path / "x.png"
    for mode in ("1", "L", "LA", "P", "RGB", "RGBA"):
        PILImage.fromarray(rgb).convert(mode).save(path)
        assert validation.check_image(path, "x.png", 10**9) == validation.ImageInfo(29, 37, "png"), mode
    PILImage.fromarray(rgb[..., 0].astype(np.uint16) * 200).save(path)  # 16 bits
    assert validation.check_image(path, "x.png", 10**9).width == 29
    # Pillow writes no interlaced PNG: one by hand, Adam7 passes of unfiltered rows
    ihdr = struct.pack(">IIBBBBB", 29, 37, 8, 2, 0, 0, 1)
    passes = b"".join(b"\0" + r.tobytes() for x, y, dx, dy in ADAM7 for r in rgb[y::dy, x::dx] if r.size)
    path.write_bytes(png(ihdr, passes))
    with PILImage.open(path) as im:
        assert im.info.get("interlace") and np.array_equal(np.asarray(im.convert("RGB")), rgb)
    assert validation.check_image(path, "x.png", 10**9).height == 37

    whole = png(struct.pack(">IIBBBBB", 29, 37, 8, 2, 0, 0, 0), b"".join(b"\0" + r.tobytes() for r in rgb))
    flipped = bytearray(whole)
    flipped[len(whole) // 2] ^= 0xFF
    short = png(struct.pack(">IIBBBBB", 29, 37, 8, 2, 0, 0, 0), b"\0" * 100)  # valid CRCs, too little data
    for label, data, message in [
        ("cut", whole[: len(whole) // 2], "truncated file"),
        ("cut before IEND", whole[:-12], "truncated file"),
        ("flipped byte", bytes(flipped), "zlib: Error -3"),  # found inflating, before the CRC
        ("too little data", short, "truncated image data (100 of"),
    ]:
        path.write_bytes(data)
        with pytest.raises(BadFile, match="truncated or corrupt image data") as e:
            validation.check_image(path, "x.png", 10**9)
        assert message in e.value.message, (label, e.value.message)


@pytest.mark.unit
def test_bmp_tiff_and_webp_checks_find_missing_data_past_the_decode_budget(tmp_path: Path) -> None:
    """Past DECODE_BUDGET the upload check does not decode, so the data a BMP's or a TIFF's
    header promises is measured against the file instead; a cut WebP fails in libwebp's demuxer
    when Pillow opens it. Whole files of each kind still pass."""
    rng = np.random.default_rng(1)
    big = PILImage.fromarray((rng.random((3000, 4000, 3)) * 255).astype(np.uint8))
    path = tmp_path / "x"
    rle = b"".join(bytes((32, y * 8)) + b"\0\0" for y in range(16)) + b"\0\1"  # 32x16, RLE8 rows
    whole_rle = bmp_header(32, 16, 8, compression=1, data_size=len(rle)) + rle
    path.write_bytes(whole_rle)
    assert validation.check_image(path, "x.bmp", 10**9) == validation.ImageInfo(32, 16, "bmp")
    with PILImage.open(path) as im:  # the RLE rows decoded as written (bottom-up)
        assert np.asarray(im)[:, 0].tolist() == [y * 8 for y in range(15, -1, -1)]
    whole = {}
    for fmt in ("BMP", "TIFF", "WEBP"):
        big.save(path, fmt, **({"quality": 10} if fmt == "WEBP" else {}))
        assert validation.check_image(path, f"x.{fmt.lower()}", 10**9).width == 4000, fmt
        whole[fmt] = path.read_bytes()
    bmp, tiff, webp = whole["BMP"], whole["TIFF"], whole["WEBP"]
    rle_head = bmp_header(4000, 3000, 8, compression=1, data_size=100_000)
    rle_unsized = bmp_header(4000, 3000, 8, compression=1)
    for label, name, data, message in [
        ("bmp header only", "x.bmp", big_bmp_cut_short(), "1000 bytes, the header promises 36000054"),
        ("bmp cut in half", "x.bmp", bmp[: len(bmp) // 2], "the header promises"),
        ("rle bmp cut", "x.bmp", rle_head + b"\0" * 100, "the header promises"),
        ("rle bmp without a size", "x.bmp", rle_unsized + b"\0" * 100, "without its data size"),
        ("tiff cut in half", "x.tiff", tiff[: len(tiff) // 2], "the strips reach byte"),
        ("webp cut in half", "x.webp", webp[: len(webp) // 2], "could not create decoder"),
    ]:
        path.write_bytes(data)
        with pytest.raises(BadFile) as e:
            validation.check_image(path, name, 10**9)
        assert message in e.value.message and str(path) not in e.value.message, (label, e.value.message)


@pytest.mark.unit
def test_project_name_pattern_is_the_use_cases_rule() -> None:
    """OpenAPI's pattern and length for a project name take exactly what the use case stores:
    every BMP character alone, between letters, and at either end, against check_project_name."""
    pattern = re.compile(validation.PROJECT_NAME_PATTERN)

    def schema_valid(name: str) -> bool:
        return pattern.fullmatch(name) is not None and len(name) <= validation.MAX_PROJECT_NAME

    def accepted(name: str) -> bool:
        try:
            validation.check_project_name(name)
        except InvalidRequest:
            return False
        return True

    for cp in [*range(0xD800), *range(0xE000, 0x10000), 0x1F600, 0x10FFFF]:
        c = chr(cp)
        for name in (c, f"a{c}b", f"{c}ab", f"ab{c}", f"{c}{c}"):
            assert schema_valid(name) == accepted(name), (hex(cp), name)
    for name in ("", " ", "a" * 200, "a" * 201, " " + "a" * 200, "\ta b\n", "a\tb"):
        assert schema_valid(name) == accepted(name), name


@pytest.mark.unit
def test_service_modules_do_not_import_torch() -> None:
    modules = (
        "service.http.api, geomatch_app.bootstrap, geomatch_app.cli, service.cli, "
        "workers.celery_queue, workers.local, workers.tasks, workers.jobs, workers.steps"
    )
    # the option vocabulary, the export table, the command's parser (the synth command's among it),
    # the survey report, a summary's finite numbers (pipeline.outputs) and the SQLite snapshot
    # (standard library only) are all the API reads of the library
    loaded = loaded_after(modules, ("torch", "geomatch", "cv2"))
    assert loaded == [
        "geomatch",
        "geomatch.cli",
        "geomatch.export",
        "geomatch.export.formats",
        "geomatch.export.source",
        "geomatch.options",
        "geomatch.pipeline",
        "geomatch.pipeline.outputs",
        "geomatch.report",
        "geomatch.sfm",
        "geomatch.sfm.sqlitecopy",
        "geomatch.synth",
        "geomatch.synth.command",
    ]


# -- feature store -------------------------------------------------------------------------------
@pytest.mark.nets
def test_features_are_computed_once_across_processes(tmp_path: Path, astronaut_pair: WarpedPair) -> None:
    """A second matcher (as in another worker process) reads the first one's features from disk:
    no network pass, identical matches."""
    store = FeatureStore(tmp_path / "features")
    a, b = astronaut_pair.image0, astronaut_pair.image1
    first = build_matcher(store, method="geo", resize=320, device="cpu")
    r1 = first.match(a, b)
    assert first.extract_calls == 4  # ALIKED and DISK for each image
    files = sorted(p.relative_to(store.root) for p in store.root.rglob("*.pt"))
    assert len(files) == 4 and {p.parts[0].split("-")[0] for p in files} == {"aliked", "disk+dense"}
    second = build_matcher(store, method="geo", resize=320, device="cpu")
    r2 = second.match(a, b)
    assert second.extract_calls == 0 and store.hits == 4  # every feature read back from disk
    np.testing.assert_array_equal(r1.keypoints0, r2.keypoints0)
    np.testing.assert_array_equal(r1.keypoints1, r2.keypoints1)
    other_resolution = build_matcher(store, method="geo", resize=256, device="cpu")
    other_resolution.features(a)
    assert other_resolution.extract_calls == 2  # resolution is part of the address


@pytest.mark.nets
def test_feature_store_prunes_least_recently_used(tmp_path: Path, astronaut_pair: WarpedPair) -> None:
    store = FeatureStore(tmp_path / "features")
    m = build_matcher(store, method="sparse", resize=256, device="cpu")
    m.features(astronaut_pair.image0)
    m.features(astronaut_pair.image1)
    files = sorted(store.root.rglob("*.pt"), key=lambda p: p.stat().st_mtime)
    assert len(files) == 2
    assert store.prune(files[-1].stat().st_size) == 1
    assert [p for p in files if p.exists()] == files[-1:]
    torn = files[-1]
    torn.write_bytes(b"not a checkpoint")  # a torn file is a miss, recomputed and rewritten
    again = build_matcher(store, method="sparse", resize=256, device="cpu")
    again.features(astronaut_pair.image1)
    assert again.extract_calls == 1 and torn.stat().st_size > 100
    off = FeatureStore(tmp_path / "off", max_bytes=0)
    build_matcher(off, method="sparse", resize=256, device="cpu").features(astronaut_pair.image0)
    assert not (tmp_path / "off").exists()


# -- job state on both metadata backends ----------------------------------------------------------
def _postgres_url() -> str | None:
    try:
        import psycopg

        with psycopg.connect(
            "postgresql://postgres@127.0.0.1:5432/postgres", connect_timeout=2, autocommit=True
        ):
            return "postgresql://postgres@127.0.0.1:5432/postgres"
    except Exception:
        return None


# the tier goes with the backend: SQLite is a file, PostgreSQL a server (skipped where none runs)
@pytest.fixture(
    params=[
        pytest.param("sqlite", marks=pytest.mark.unit),
        pytest.param("postgresql", marks=pytest.mark.service),
    ]
)
def store(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[MetadataStore]:
    if request.param == "sqlite":
        s = MetadataStore(f"sqlite:///{tmp_path / 'meta.sqlite'}")
        s.create_all()
        yield s
        s.dispose()
        return
    admin = _postgres_url()
    if admin is None:
        pytest.skip("no PostgreSQL on 127.0.0.1:5432")
    import psycopg

    name = f"gmtest_{uuid.uuid4().hex[:12]}"
    with psycopg.connect(admin, autocommit=True) as c:
        c.execute(f"CREATE DATABASE {name}")
    s = MetadataStore(admin.rsplit("/", 1)[0] + f"/{name}")
    try:
        s.create_all()
        yield s
    finally:
        s.dispose()
        with psycopg.connect(admin, autocommit=True) as c:
            c.execute(f"DROP DATABASE {name} WITH (FORCE)")


def _match_job(store: MetadataStore, pairs: int) -> str:
    with store.session() as s:
        t = Tenant(name=f"t-{uuid.uuid4().hex[:6]}")
        s.add(t)
        s.flush()
        p = Project(tenant_id=t.id, name="p", config={})
        s.add(p)
        s.flush()
        j = Job(project_id=p.id, tenant_id=t.id, kind="match", options={})
        s.add(j)
        s.flush()
        s.add_all(JobPair(job_id=j.id, idx=i, name0=f"{i}a", name1=f"{i}b") for i in range(pairs))
        j.total, j.planned = pairs, True
        return j.id


def test_pairs_count_once_and_jobs_finish_once(store: MetadataStore) -> None:
    job_id = _match_job(store, 2)
    assert jobstate.claim(store, job_id) is not None
    assert jobstate.mark_pair_done(store, job_id, 0, 10, 8)
    assert not jobstate.mark_pair_done(store, job_id, 0, 10, 8)  # a redelivered step
    assert not jobstate.finish_if_complete(store, job_id)
    assert jobstate.mark_pair_done(store, job_id, 1, 5, 5)
    assert jobstate.finish_if_complete(store, job_id)
    assert not jobstate.finish_if_complete(store, job_id)  # exactly one caller sees the end
    job = jobstate.get(store, job_id)
    assert job is not None and (job.state, job.done, job.total) == ("succeeded", 2, 2)
    assert jobstate.claim(store, job_id) is None  # finished jobs are not run again


def test_a_jobs_window_hands_out_each_pair_once_and_no_more_than_it_holds(store: MetadataStore) -> None:
    job_id = _match_job(store, 7)
    assert jobstate.claim_pairs(store, job_id, 3) == []  # queued: nothing handed out before it runs
    assert jobstate.claim(store, job_id) is not None
    assert jobstate.claim_pairs(store, job_id, 3) == [0, 1, 2]
    assert jobstate.claim_pairs(store, job_id, 3) == []  # the window is full
    jobstate.mark_pair_done(store, job_id, 1, 1, 1)
    assert jobstate.claim_pairs(store, job_id, 3) == [3]  # one ended, one more
    # steps ending together on several threads: every pair handed out exactly once
    handed: list[int] = []
    lock = threading.Lock()

    def step_loop() -> None:
        while True:
            with lock:
                mine = [i for i in handed_now if i not in taken]
                taken.update(mine)
            for i in mine:
                jobstate.mark_pair_done(store, job_id, i, 1, 1)
            got = jobstate.claim_pairs(store, job_id, 3)
            with lock:
                handed.extend(got)
                handed_now.extend(got)
                if not got and len(taken) == 7:
                    return
            if not got:
                time.sleep(0.01)

    taken: set[int] = {1}
    handed_now: list[int] = [0, 2, 3]
    threads = [threading.Thread(target=step_loop) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    assert sorted(handed) == [4, 5, 6]
    job = jobstate.get(store, job_id)
    assert job is not None and (job.done, job.dispatched) == (7, 7)
    assert jobstate.finish_if_complete(store, job_id)
    assert jobstate.claim_pairs(store, job_id, 3) == []  # finished


def test_a_tenants_queued_pairs_count_planned_rows_not_done(store: MetadataStore) -> None:
    job_id = _match_job(store, 5)
    with store.session() as s:
        tenant = s.scalar(select(Job.tenant_id).where(Job.id == job_id))
    assert jobstate.queued_pairs(store, tenant)[:2] == (5, 1)
    jobstate.claim(store, job_id)
    jobstate.mark_pair_done(store, job_id, 0, 1, 1)
    assert jobstate.queued_pairs(store, tenant)[:2] == (4, 1)
    assert jobstate.queued_pairs(store, tenant, other_than=job_id)[:2] == (0, 0)
    jobstate.cancel(store, job_id)
    assert jobstate.queued_pairs(store, tenant)[:2] == (0, 0)
    message = too_much_queued(4, 1, 10, 12)
    assert "limit of 12 queued pairs per tenant" in message and "GEOMATCH_MAX_QUEUED_PAIRS" in message


def test_terminal_states_are_final(store: MetadataStore) -> None:
    job_id = _match_job(store, 1)
    assert jobstate.cancel(store, job_id, "by test")
    assert jobstate.claim(store, job_id) is None
    assert not jobstate.fail(store, job_id, "too late")
    jobstate.mark_pair_done(store, job_id, 0, 1, 1)
    assert not jobstate.finish_if_complete(store, job_id)
    with store.session() as s:
        assert s.scalar(select(Job.state).where(Job.id == job_id)) == "cancelled"


@pytest.mark.unit
def test_retry_policy() -> None:
    """Bad data, bad options and missing weights fail a job at once; I/O and the like are retried."""
    from geomatch.features.weights import WeightsNotFoundError
    from geomatch.imageio import ImageReadError
    from workers.context import PermanentError, is_permanent

    for exc in (
        ValueError("x"),
        ImageReadError("x"),
        PermanentError("x"),
        WeightsNotFoundError("x"),
        KeyError(1),
    ):
        assert is_permanent(exc), exc
    for exc in (OSError("disk"), ConnectionError("redis"), RuntimeError("out of memory"), TimeoutError()):
        assert not is_permanent(exc), exc


@pytest.mark.unit
def test_the_job_list_filters_by_the_states_jobs_have() -> None:
    """The REST route's ``state`` choices (its OpenAPI enum) are the store's job states."""
    import typing

    from geomatch_core.models import JOB_STATES
    from service.http.routes.jobs import list_jobs

    hint = typing.get_type_hints(list_jobs, include_extras=True)["state"]
    literal = typing.get_args(typing.get_args(hint)[0])[0]
    assert typing.get_args(literal) == JOB_STATES


def test_localize_progress_moves_up_only_while_running(store: MetadataStore) -> None:
    """A localize job counts its photos itself: a late or repeated report (a redelivered step
    starting over) never rewinds the count, and none moves a finished job."""
    job_id = _match_job(store, 0)
    with store.session() as s:
        job = s.get(Job, job_id)
        assert job is not None
        job.kind, job.total = "localize", 3
    assert not jobstate.set_progress(store, job_id, 1)  # queued: not yet
    assert jobstate.claim(store, job_id) is not None
    assert jobstate.set_progress(store, job_id, 2)
    assert not jobstate.set_progress(store, job_id, 1)
    assert jobstate.succeed(store, job_id, {"localizations": []})
    assert not jobstate.set_progress(store, job_id, 3)
    job = jobstate.get(store, job_id)
    assert job is not None and (job.state, job.done) == ("succeeded", 3)


@pytest.mark.unit
def test_localization_answers_keep_every_field_over_rest_and_grpc() -> None:
    """The library's answers, placed and not, as the REST schema and the gRPC message carry them:
    nothing of a pose is invented for a photo that was not localized."""
    from geomatch.localize import Localization
    from service.grpcapi import convert
    from service.http.schemas import LocalizationOut

    placed = Localization(
        name="new.jpg",
        localized=True,
        reason=None,
        cam_from_world={"qvec": [1.0, 0.0, 0.0, 0.0], "tvec": [1.0, 2.0, 3.0]},
        center=[-1.0, -2.0, -3.0],
        wgs84={"lat": 47.1, "lon": 8.5, "alt": 410.0, "heading_deg": 93.5},
        inliers=120,
        matches=300,
        reprojection_error_px=0.8,
        confidence="high",
        supporting_images=["a.png", "b.png"],
        camera={"model": "SIMPLE_RADIAL", "width": 640, "height": 480, "params": [576.0, 320.0, 240.0, 0.0]},
        seconds=2.5,
        candidates=["a.png", "b.png", "c.png"],
        inlier_ratio=0.4,
        focal_source="model",
    ).to_json()
    lost = Localization(
        name="cup.png",
        localized=False,
        reason="no match with the model's 3D points",
        cam_from_world=None,
        center=None,
        wgs84=None,
        inliers=0,
        matches=2,
        reprojection_error_px=None,
        confidence="none",
        supporting_images=[],
        camera=None,
        seconds=1.0,
    ).to_json()
    assert LocalizationOut.model_validate(placed).model_dump() == placed
    assert LocalizationOut.model_validate(lost).model_dump() == lost
    m = convert.localization(placed)
    assert (m.name, m.localized, m.confidence, m.inliers, m.matches) == ("new.jpg", True, "high", 120, 300)
    assert list(m.cam_from_world.qvec) == [1.0, 0.0, 0.0, 0.0] and list(m.center) == [-1.0, -2.0, -3.0]
    assert (m.wgs84.lat, m.wgs84.lon, m.wgs84.heading_deg) == (47.1, 8.5, 93.5)
    assert m.camera.model == "SIMPLE_RADIAL" and list(m.camera.params) == [576.0, 320.0, 240.0, 0.0]
    assert m.reprojection_error_px == 0.8 and list(m.supporting_images) == ["a.png", "b.png"]
    n = convert.localization(lost)
    assert not n.localized and n.reason == lost["reason"] and n.confidence == "none"
    for field in ("cam_from_world", "wgs84", "camera", "reprojection_error_px"):
        assert not n.HasField(field), field
    assert list(n.center) == []
