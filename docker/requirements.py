"""Print the image's pip requirements: the package's dependencies from pyproject.toml, for one
torch variant (``cpu``, ``cu126``, ``cu130`` ...).

The Dockerfile installs these in a layer of their own, before the source is copied, so that a
source edit does not reinstall a few GB of wheels. Two dependencies change with the variant:

- torch is pinned to exactly the build already installed from the variant's index: a range left
  open would let pip swap it for PyPI's default wheel (CUDA 13 and several GB of CUDA packages),
  or a CUDA wheel into the CPU image; pinned, a range that excludes it fails the build instead.
- pycolmap becomes ``pycolmap-cuda12`` (the same ``pycolmap`` module, built with CUDA) on CUDA 12
  variants. PyPI has no CUDA 13 build of pycolmap, so CUDA 13 variants keep the CPU build
  (networks on the GPU, mapping on the CPU).

``--build`` prints the build-system requirements instead: the package is built without build
isolation, so that setup.py generates the gRPC code with the grpcio-tools installed beside the
protobuf runtime that will import it.

Usage: python requirements.py PYPROJECT VARIANT > requirements.txt
       python requirements.py --build PYPROJECT > build-requirements.txt
"""

from __future__ import annotations

import re
import sys
import tomllib
from importlib.metadata import PackageNotFoundError, version

_NAME = re.compile(r"^\s*([A-Za-z0-9][A-Za-z0-9._-]*)(.*)$")
_VARIANT = re.compile(r"^(cpu|cu(\d\d)(\d+))$")


def canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def cuda_major(variant: str) -> int | None:
    """12 for cu126, 13 for cu130; None for cpu."""
    m = _VARIANT.match(variant)
    if m is None:
        raise ValueError(f"TORCH_VARIANT={variant!r}: expected cpu or cuXY (cu126, cu130, ...)")
    return None if m.group(1) == "cpu" else int(m.group(2))


def requirements(pyproject: str, variant: str, torch_version: str | None) -> list[str]:
    with open(pyproject, "rb") as f:
        deps = tomllib.load(f)["project"]["dependencies"]
    major = cuda_major(variant)
    out = []
    for dep in deps:
        m = _NAME.match(dep)
        if m is None:
            raise ValueError(f"cannot read the dependency {dep!r}")
        name, rest = m.group(1), m.group(2)
        if canonical(name) == "torch":
            if torch_version is None:
                raise ValueError("torch is not installed: install it from the variant's index first")
            out.append(f"torch=={torch_version}")
        elif canonical(name) == "pycolmap" and major == 12:
            out.append(f"pycolmap-cuda12{rest}")
        else:
            out.append(dep)
    return out


def build_requirements(pyproject: str) -> list[str]:
    with open(pyproject, "rb") as f:
        return list(tomllib.load(f)["build-system"]["requires"])


def main(argv: list[str]) -> int:
    if len(argv) == 2 and argv[0] == "--build":
        print("\n".join(build_requirements(argv[1])))
        return 0
    if len(argv) != 2:
        print(__doc__, file=sys.stderr)
        return 2
    try:
        torch_version: str | None = version("torch")
    except PackageNotFoundError:
        torch_version = None
    try:
        lines = requirements(argv[0], argv[1], torch_version)
    except ValueError as e:
        print(f"requirements.py: error: {e}", file=sys.stderr)
        return 1
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
