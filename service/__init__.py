"""The geomatch service: HTTP (FastAPI) and gRPC over one application layer (``usecases``), auth,
the batch client. Built on ``geomatch_core`` (models, job states, storage); it never imports ``workers``:
the composition root (``geomatch_app``) hands it a job queue.

Of the library it reads ``geomatch.options`` only (no torch): heavy work runs in ``workers``.
"""
