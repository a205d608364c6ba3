"""The export formats are one table (``geomatch.export.formats``): the proto's ModelFormat agrees
with it, and a row added to it appears in ``geomatch export``'s choices and help, in the REST
schema and the use cases, and in the proto check (which then asks for its enum line)."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import pytest

from geomatch.export.formats import FORMATS, ExportFormat, register, unregister
from geomatch_app.bootstrap import build_service, close_service
from geomatch_core.config import Settings
from service.clients.grpc_client import FORMAT
from service.grpcapi import convert
from service.grpcapi.pb import pb2
from service.http.api import create_app
from service.usecases.outputs import model_formats

pytestmark = pytest.mark.unit

ROOT = Path(__file__).resolve().parents[1]
PROTO = ROOT / "proto" / "geomatch" / "v1" / "geomatch.proto"
THROWAWAY = ExportFormat(
    "throwaway-ply",
    "geomatch.export.ply:write",
    frozenset(),
    "application/zip",
    "a test's second name for ply",
    99,
)


def proto_enum(name: str) -> dict[str, int]:
    """An enum of the proto file as it is written (value name -> number)."""
    body = re.search(rf"enum {name} \{{(.*?)\n\}}", PROTO.read_text(), re.S)
    assert body is not None, name
    return {k: int(v) for k, v in re.findall(r"^\s*(\w+)\s*=\s*(\d+);", body.group(1), re.M)}


def test_proto_enum_is_the_table() -> None:
    enum = proto_enum("ModelFormat")
    assert convert.enum_problems(FORMATS.values(), enum) == []
    assert enum == dict(pb2.ModelFormat.items())  # the generated code is the file's
    assert set(FORMAT) == set(model_formats())  # the client names what the service serves


def test_proto_check_names_what_disagrees() -> None:
    enum = proto_enum("ModelFormat")
    renumbered = {**enum, "MODEL_FORMAT_HLOC": 9}
    assert convert.enum_problems(FORMATS.values(), renumbered) == [
        "MODEL_FORMAT_HLOC is 9 in the proto, 6 in the export table (hloc)"
    ]
    extra = {**enum, "MODEL_FORMAT_OBJ": 8}
    assert convert.enum_problems(FORMATS.values(), extra) == [
        "MODEL_FORMAT_OBJ of the proto's ModelFormat is no export format (geomatch.export.formats)"
    ]


@pytest.fixture
def throwaway() -> Iterator[ExportFormat]:
    register(THROWAWAY)
    try:
        yield THROWAWAY
    finally:
        unregister(THROWAWAY.name)


def export_help(capsys: pytest.CaptureFixture[str]) -> str:
    from geomatch_app.cli import main  # the whole `geomatch` command

    with pytest.raises(SystemExit):
        main(["export", "--help"])
    return " ".join(capsys.readouterr().out.split())


def model_format_schema(tmp_path: Path) -> dict[str, object]:
    settings = Settings(home=tmp_path, database_url=f"sqlite:///{tmp_path / 'db.sqlite'}", redis_url=None)
    service = build_service(settings)
    try:
        operation = create_app(service).openapi()["paths"]["/v1/projects/{project_id}/model"]["get"]
    finally:
        close_service(service)
    return next(p for p in operation["parameters"] if p["name"] == "format")  # type: ignore[no-any-return]


def test_a_row_is_a_new_format_everywhere(
    throwaway: ExportFormat, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text = export_help(capsys)
    assert "throwaway-ply" in text and "a test's second name for ply" in text
    schema = model_format_schema(tmp_path)
    assert schema["schema"]["enum"][-1] == "throwaway-ply"  # type: ignore[index]
    assert "throwaway-ply: a test's second name for ply" in str(schema["description"])
    assert model_formats()[-1] == "throwaway-ply"
    # the proto is static text: the check asks for the row's enum line
    assert convert.enum_problems(FORMATS.values(), proto_enum("ModelFormat")) == [
        "MODEL_FORMAT_THROWAWAY_PLY (throwaway-ply, 99 in the export table) is not in the proto's ModelFormat"
    ]


def test_a_row_names_its_writer() -> None:
    """A row's writer is imported when its format is written, by the name the row gives."""
    from geomatch.export import ply

    assert THROWAWAY.load() is ply.write
    assert all(callable(f.load()) for f in FORMATS.values())


def test_the_row_leaves_with_unregister(capsys: pytest.CaptureFixture[str]) -> None:
    assert "throwaway-ply" not in export_help(capsys)
    assert "throwaway-ply" not in model_formats()
