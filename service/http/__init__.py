"""The REST transport: the FastAPI app (``api``), its routes, schemas, middleware (body limits,
security headers, metrics), the HTTP protocol uvicorn runs and the web console it serves.

It translates requests into calls of ``service.usecases`` and typed errors into statuses, as
``service.grpcapi`` does for gRPC; what both transports use (auth, paging, validation, slots) stays
in ``service``.
"""
