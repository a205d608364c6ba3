"""The geomatch service: REST (``http``, FastAPI) and gRPC (``grpcapi``) over one application layer
(``usecases``), what both transports share (auth, paging, validation, rate limits, slots), and the
clients (``clients``: REST, gRPC, the batch flow of ``geomatch submit``). Built on ``geomatch_core``
(models, job states, storage); it never imports ``workers``: the composition root
(``geomatch_app``) hands it a job queue.

Of the library it reads ``geomatch.options`` only (no torch): heavy work runs in ``workers``.
"""
