"""Generate the gRPC Python code from ``proto/geomatch/v1/geomatch.proto`` into this package.

The generated modules are build products, never committed or edited: ``make setup`` runs this
module with the virtual environment's grpcio-tools (so the generated code matches the installed
protobuf and grpcio), and ``setup.py`` runs it when a wheel is built. It imports nothing but the
standard library at module level, so ``setup.py`` can load it by path before anything is installed.

protoc names Python modules after the proto's path: the stub module would import
``geomatch.v1.geomatch_pb2``, which is the ``geomatch`` library's namespace here. The files are
generated into a scratch folder and placed flat in this package, and the stub's one import of its
messages becomes a relative import: a mechanical rewrite, checked to have happened.
"""

from __future__ import annotations

import hashlib
import re
import shutil
import sys
import tempfile
from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parent
PROTO_ROOT = PACKAGE_DIR.parent.parent / "proto"
PROTO = Path("geomatch/v1/geomatch.proto")  # relative to PROTO_ROOT: the name it is registered under
OUTPUTS = ("geomatch_pb2.py", "geomatch_pb2.pyi", "geomatch_pb2_grpc.py")
STAMP = "geomatch_proto_sha256.txt"  # the proto's digest at generation time: staleness check
_STUB_IMPORT = re.compile(r"^from geomatch\.v1 import geomatch_pb2 as (\w+)$", re.MULTILINE)


def proto_digest(proto_root: Path | None = None) -> str:
    return hashlib.sha256(((proto_root or PROTO_ROOT) / PROTO).read_bytes()).hexdigest()


def generate(proto_root: Path | None = None, out_dir: Path | None = None) -> list[Path]:
    """Run protoc (grpcio-tools) and write the modules into ``out_dir`` (default: this package)."""
    proto_root, out_dir = proto_root or PROTO_ROOT, out_dir or PACKAGE_DIR
    try:
        import grpc_tools
        from grpc_tools import protoc
    except ImportError:
        raise RuntimeError(
            "grpcio-tools is not installed: `pip install grpcio-tools` (a dependency of geomatch)"
        ) from None
    if not (proto_root / PROTO).is_file():
        raise RuntimeError(f"{proto_root / PROTO}: no such file")
    well_known = Path(grpc_tools.__file__).parent / "_proto"  # google/protobuf/*.proto
    with tempfile.TemporaryDirectory(prefix="geomatch-protoc-") as tmp:
        args = [
            "grpc_tools.protoc",
            f"-I{proto_root}",
            f"-I{well_known}",
            f"--python_out={tmp}",
            f"--pyi_out={tmp}",
            f"--grpc_python_out={tmp}",
            str(PROTO),
        ]
        if protoc.main(args) != 0:
            raise RuntimeError(f"protoc failed on {proto_root / PROTO} (its messages are above)")
        generated = Path(tmp) / PROTO.parent
        stub = generated / "geomatch_pb2_grpc.py"
        text, n = _STUB_IMPORT.subn(r"from . import geomatch_pb2 as \1", stub.read_text())
        if n != 1:
            raise RuntimeError(f"{stub.name}: expected one import of geomatch_pb2 to rewrite, found {n}")
        stub.write_text(text)
        out_dir.mkdir(parents=True, exist_ok=True)
        written = []
        for name in OUTPUTS:
            dest = out_dir / name
            shutil.copyfile(generated / name, dest.with_suffix(dest.suffix + ".tmp"))
            dest.with_suffix(dest.suffix + ".tmp").replace(dest)  # importers never see half a file
            written.append(dest)
    (out_dir / STAMP).write_text(proto_digest(proto_root) + "\n")
    return written


def main() -> int:
    try:
        for path in generate():
            print(f"generated {path}")
    except RuntimeError as e:
        print(f"geomatch: error: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
