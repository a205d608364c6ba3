"""What every route depends on: the service of the app, the tenant of the request's API key, and
the error responses every route documents."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from ..schemas import Error
from ..usecases import Service

_bearer = HTTPBearer(auto_error=False, description="an API key from `geomatch keys create TENANT`")
ERRORS: dict[int | str, dict[str, object]] = {
    code: {"model": Error} for code in (400, 401, 404, 409, 413, 415, 422, 503)
}


def service(request: Request) -> Service:
    return request.app.state.service  # type: ignore[no-any-return]  # Starlette's State holds Any


def tenant(
    request: Request, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]
) -> str:
    key = credentials.credentials if credentials and credentials.scheme.lower() == "bearer" else None
    return service(request).authenticate(key)


Svc = Annotated[Service, Depends(service)]
Tenant = Annotated[str, Depends(tenant)]
