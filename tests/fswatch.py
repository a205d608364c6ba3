"""What a block of code opened on the file system, as strace would see it, for the tests that prove
request text never reaches a file."""

from __future__ import annotations

import ctypes
import os
import struct
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

IN_ACCESS, IN_OPEN = 0x1, 0x20


@contextmanager
def watched(folder: Path) -> Iterator[list[str]]:
    """Every open or read of a file in ``folder`` while the block runs, by any code of any process
    (inotify, as strace would see the syscalls; PROJ opens its files in C, where Python's audit
    hooks see nothing), plus Python's own opens of paths under it (an audit hook)."""
    libc = ctypes.CDLL(None, use_errno=True)
    fd = libc.inotify_init1(os.O_NONBLOCK)
    assert fd >= 0, os.strerror(ctypes.get_errno())
    assert libc.inotify_add_watch(fd, str(folder).encode(), IN_OPEN | IN_ACCESS) >= 0
    seen: list[str] = []
    active = [True]

    def hook(event: str, args: tuple[object, ...]) -> None:
        if active[0] and event == "open" and args and str(folder) in str(args[0]):
            seen.append(f"python open {args[0]}")

    sys.addaudithook(hook)  # a hook stays for the process: ``active`` turns it off after the block
    try:
        yield seen
    finally:
        active[0] = False
        try:
            data = os.read(fd, 1 << 16)
        except BlockingIOError:
            data = b""
        os.close(fd)
        while data:  # struct inotify_event: wd, mask, cookie, len, name[len]
            _, mask, _, n = struct.unpack_from("iIII", data)
            name = data[16 : 16 + n].rstrip(b"\0").decode()
            seen.append(f"inotify {mask:#x} {name}")
            data = data[16 + n :]
