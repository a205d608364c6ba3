"""The composition root: the ``geomatch`` command (``geomatch_app.cli``) and the wiring of a
service to a job runner (``geomatch_app.bootstrap``, ``geomatch_app.asgi``). The only package that
names both ``service`` and ``workers``."""
