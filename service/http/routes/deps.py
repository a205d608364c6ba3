"""What every route depends on: the service of the app, the tenant of the request's API key, and
the error responses every route documents."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request, Response
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from ...usecases import Service
from ..schemas import Error

_bearer = HTTPBearer(auto_error=False, description="an API key from `geomatch keys create TENANT`")
ERRORS: dict[int | str, dict[str, object]] = {
    code: {"model": Error} for code in (400, 401, 403, 404, 409, 413, 415, 422, 429, 503)
}


MAX_OFFSET = 10**12  # past any list; keeps the offset an integer every store takes


def link_next(request: Request, response: Response, next_offset: int | None, limit: int) -> None:
    """``Link: <same URL, next offset>; rel="next"`` when another page exists (RFC 8288)."""
    if next_offset is not None:
        url = request.url.include_query_params(offset=next_offset, limit=limit)
        response.headers["Link"] = f'<{url.path}?{url.query}>; rel="next"'


def service(request: Request) -> Service:
    return request.app.state.service  # type: ignore[no-any-return]  # Starlette's State holds Any


def tenant(
    request: Request, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]
) -> str:
    checked = request.scope.get("state", {}).get("tenant_id")  # by bodylimits, before the body
    if checked is not None:
        return str(checked)
    key = credentials.credentials if credentials and credentials.scheme.lower() == "bearer" else None
    return service(request).authenticate(key)


Svc = Annotated[Service, Depends(service)]
Tenant = Annotated[str, Depends(tenant)]
