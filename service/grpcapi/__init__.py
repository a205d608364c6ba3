"""The gRPC adapter: ``geomatch.v1.Matching`` over the same use cases as the REST routes.

Importing this package imports nothing generated: ``codegen`` must run before the generated
modules exist, and ``pb`` is where their absence becomes a clear error.
"""
