"""The composition root: the ``geomatch`` command (``app.cli``) and the wiring of a service to a
job runner (``app.bootstrap``, ``app.asgi``). The only package that names both ``service`` and
``workers``."""
