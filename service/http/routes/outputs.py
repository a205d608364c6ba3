"""/v1/projects/{id}/model, /report, /database, /pairs and a pair's matches.png.

The router is made with each app (:func:`router`): the model's formats are the export table's
(``geomatch.export.formats``) as it is then, and the OpenAPI schema lists them.
"""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query, Response
from fastapi.responses import FileResponse, JSONResponse
from starlette.background import BackgroundTask

from geomatch.report import to_markdown

from ...usecases.outputs import export_formats, model_files, remove_quietly
from ..schemas import PairOut, PairsOut, SceneOut
from .deps import Svc, Tenant

SCENE = "scene"  # computed from the model's text files for a viewer, not a stored file


def router() -> APIRouter:
    out = APIRouter(tags=["outputs"])
    files, exports = model_files(), export_formats()
    media = {m.name: m.media_type for m in files} | {f.name: f.media_type for f in exports}
    names = (*(m.name for m in files), SCENE, *(f.name for f in exports))
    described = (
        ", ".join(f"{m.name}: {m.help}" for m in files)
        + f", {SCENE}: points and cameras for a viewer; zips for other tools (docs/exports.md), built on "
        + "first request: "
        + ", ".join(f"{f.name}: {f.help}" for f in exports)
    )

    def model(project_id: str, svc: Svc, tenant_id: Tenant, format: str = "zip") -> Response:
        if format == SCENE:
            scene = SceneOut.model_validate(svc.outputs.model_scene(tenant_id, project_id))
            return Response(scene.model_dump_json(), media_type="application/json")
        path = svc.outputs.model_file(tenant_id, project_id, format)
        return FileResponse(path, media_type=media[format], filename=f"{project_id}-{path.name}")

    # the formats are known only now, and this module's annotations are strings resolved in its
    # globals: the parameter's type is set on the function itself
    model.__annotations__["format"] = Annotated[Literal[names], Query(description=described)]
    out.add_api_route(
        "/projects/{project_id}/model",
        model,
        methods=["GET"],
        response_class=FileResponse,
        responses={200: {"content": {m: {} for m in media.values()}}},
    )
    out.add_api_route(
        "/projects/{project_id}/report",
        report,
        methods=["GET"],
        response_class=JSONResponse,
        responses={
            200: {
                "description": "the report: JSON (format=json) or a Markdown page (format=md)",
                "content": {
                    "application/json": {"schema": {"type": "object"}},
                    MARKDOWN: {"schema": {"type": "string"}},
                },
            }
        },
    )
    out.add_api_route(
        "/projects/{project_id}/database",
        database,
        methods=["GET"],
        response_class=FileResponse,
        responses={200: {"content": {"application/vnd.sqlite3": {}}}},
    )
    out.add_api_route("/projects/{project_id}/pairs", list_pairs, methods=["GET"], response_model=PairsOut)
    out.add_api_route(
        "/projects/{project_id}/pairs/{name0}/{name1}/matches.png",
        matches_png,
        methods=["GET"],
        response_class=FileResponse,
        responses={200: {"content": {"image/png": {}}}},
    )
    return out


MARKDOWN = "text/markdown"


def report(
    project_id: str,
    svc: Svc,
    tenant_id: Tenant,
    format: Annotated[
        Literal["json", "md"], Query(description="json: the report's fields; md: the page to read")
    ] = "json",
) -> Response:
    """The survey report of the project's model (photos registered and left out, points and track
    lengths, reprojection error, the fit to the photos' GPS and to the ground control points with
    the check-point RMSE, pairs the view-graph checks dropped, time per stage): the reconstruct
    job's ``report`` (a model made before reports is reported from its summary). 404 before the
    first model."""
    view = svc.outputs.survey_report(tenant_id, project_id)
    if format == "md":
        page = to_markdown(view.report, title=f"Survey report: {view.project_name}")
        return Response(page, media_type=f"{MARKDOWN}; charset=utf-8")
    return JSONResponse(view.report)


def database(project_id: str, svc: Svc, tenant_id: Tenant) -> FileResponse:
    path = svc.outputs.database_snapshot(tenant_id, project_id)
    return FileResponse(
        path,
        media_type="application/vnd.sqlite3",
        filename=f"{project_id}-database.db",
        background=BackgroundTask(remove_quietly, path),
    )


def list_pairs(project_id: str, svc: Svc, tenant_id: Tenant) -> PairsOut:
    """Matched pairs with their counts, most verified matches first (empty before matching)."""
    views = svc.outputs.list_pairs(tenant_id, project_id)
    return PairsOut(pairs=[PairOut.model_validate(v, from_attributes=True) for v in views])


def matches_png(project_id: str, name0: str, name1: str, svc: Svc, tenant_id: Tenant) -> FileResponse:
    return FileResponse(
        svc.outputs.matches_picture(tenant_id, project_id, name0, name1), media_type="image/png"
    )
