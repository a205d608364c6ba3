"""Build hook: the gRPC code is generated from proto/ whenever the package is built or installed.

Everything else about the package is in pyproject.toml. ``build_py`` runs for wheels and for
editable installs alike; it generates into service/grpcapi/ before the package's modules are
collected, so the generated modules ship in the wheel (and are importable from the source tree in
editable mode). The generator is loaded by path: nothing of the package is importable yet.
"""

import importlib.util
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

ROOT = Path(__file__).resolve().parent


class BuildPyWithProto(build_py):
    def run(self) -> None:
        spec = importlib.util.spec_from_file_location("_codegen", ROOT / "service" / "grpcapi" / "codegen.py")
        assert spec is not None and spec.loader is not None
        codegen = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(codegen)
        for path in codegen.generate():
            print(f"generated {path.relative_to(ROOT)}")
        super().run()


setup(cmdclass={"build_py": BuildPyWithProto})
