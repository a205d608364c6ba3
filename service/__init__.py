"""The geomatch service: HTTP API over one application layer, metadata store, file storage, auth.

Nothing here imports torch or the ``geomatch`` library: heavy work runs in ``workers`` (Celery
processes, or in-process threads in the embedded default), which import the library lazily.
"""
