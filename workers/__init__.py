"""The queue side: Celery on Redis (or in-process threads when embedded) running the job steps
(``workers.steps``, one static table), which call the ``geomatch`` library. Built on ``geomatch_core``; it
never imports ``service``. Importing this package does not import torch."""
