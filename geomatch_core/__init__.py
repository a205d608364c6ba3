"""The core shared by the service and the workers: settings, metadata models and store, job
states, step names and the queue protocol, file storage paths, writer locks, typed errors.

It imports neither the servers' frameworks nor the library's networks; ``service`` and ``workers``
both build on it and never on each other (``tests/test_layers.py``)."""
