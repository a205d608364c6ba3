"""The queue side: Celery on Redis (or in-process threads when embedded) running the job steps,
which call the ``geomatch`` library. Importing this package does not import torch."""
