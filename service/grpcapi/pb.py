"""The generated modules, or an error that says how to make them.

They are build products (``make setup``, or ``setup.py`` when a wheel is built): a fresh checkout
without them, or a proto edited since they were made, fails here with the command to run instead
of with an ImportError deep in a stub.
"""

from __future__ import annotations

from types import ModuleType
from typing import TYPE_CHECKING

from . import codegen

__all__ = ["SERVICE", "SERVICE_NAME", "GeneratedCodeMissing", "pb2", "pb2_grpc"]


class GeneratedCodeMissing(RuntimeError):
    pass


_HOW = "run `make setup` (or `python -m service.grpcapi.codegen`)"


def _load() -> tuple[ModuleType, ModuleType]:
    try:
        from . import geomatch_pb2, geomatch_pb2_grpc
    except ImportError as e:
        raise GeneratedCodeMissing(f"the gRPC code generated from proto/ is missing ({e}): {_HOW}") from None
    stamp = codegen.PACKAGE_DIR / codegen.STAMP
    source = codegen.PROTO_ROOT / codegen.PROTO
    if source.is_file() and stamp.is_file() and stamp.read_text().strip() != codegen.proto_digest():
        raise GeneratedCodeMissing(f"{source} changed since its gRPC code was generated: {_HOW}")
    return geomatch_pb2, geomatch_pb2_grpc


if TYPE_CHECKING:
    # the checker reads the generated modules themselves (the messages' classes are in protoc's
    # geomatch_pb2.pyi); at run time they come through _load and its checks
    from . import geomatch_pb2 as pb2
    from . import geomatch_pb2_grpc as pb2_grpc
else:
    pb2, pb2_grpc = _load()
SERVICE = pb2.DESCRIPTOR.services_by_name["Matching"]
SERVICE_NAME: str = SERVICE.full_name  # "geomatch.v1.Matching"
