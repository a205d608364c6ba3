"""What a fresh interpreter has loaded after some imports: the check that a process (the API,
the service's export builders) stays free of torch and friends, shared by the tests that make it."""

from __future__ import annotations

import ast
import subprocess
import sys


def loaded_after(imports: str, roots: tuple[str, ...]) -> list[str]:
    """The sorted names in ``sys.modules`` whose top-level package is one of ``roots``, in a new
    interpreter that ran ``import sys, <imports>``."""
    code = f"import sys, {imports}; print(sorted(m for m in sys.modules if m.split('.')[0] in {roots!r}))"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return ast.literal_eval(r.stdout.strip())
