"""A folder of drone photos through geomatch's NodeODM node with PyODM, as a WebODM user's script
would send them: create the task (photos, and a gcp_list.txt when the folder has one), wait for
it, download its assets, and print the wall time, the task's own processing time and the files
received (docs/webodm.md).

    geomatch serve &                    # the node on :3000, prints the API key (embedded mode)
    .venv/bin/python bench/nodeodm_run.py ../shared/data/real/drone/brighton_beach_full/images \\
        --token KEY --out /tmp/brighton-assets

Options go as NodeODM options (``--option resize=1024``); names the node does not list are
dropped by the node, as NodeODM drops them.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from pyodm import Node

PHOTOS = {".jpg", ".jpeg", ".png", ".tif", ".tiff"}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("images", type=Path, help="a folder of photos (and optionally gcp_list.txt)")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=3000)
    p.add_argument("--token", required=True, help="an API key of the geomatch service")
    p.add_argument("--out", type=Path, required=True, help="where the assets are extracted")
    p.add_argument("--option", action="append", default=[], metavar="NAME=VALUE")
    p.add_argument("--name", default=None)
    args = p.parse_args(argv)

    files = sorted(str(f) for f in args.images.iterdir() if f.suffix.lower() in PHOTOS)
    if (args.images / "gcp_list.txt").is_file():
        files.append(str(args.images / "gcp_list.txt"))
    options = dict(o.split("=", 1) for o in args.option)
    node = Node(args.host, args.port, token=args.token)
    info = node.info()
    print(f"node {info.engine} {info.engine_version} (API {info.version}), {len(files)} files", flush=True)

    t0 = time.perf_counter()
    task = node.create_task(files, options, name=args.name or args.images.parent.name)
    uploaded = time.perf_counter() - t0
    print(f"task {task.uuid}: uploaded in {uploaded:.1f} s", flush=True)
    last = [-1]

    def status(i: object) -> None:
        progress = int(getattr(i, "progress", 0))
        if progress != last[0]:
            last[0] = progress
            print(
                f"  {time.perf_counter() - t0:7.1f} s  {getattr(i, 'status', '?')}  {progress} %", flush=True
            )

    task.wait_for_completion(status_callback=status, interval=3)
    done = time.perf_counter() - t0
    task.download_assets(str(args.out))
    total = time.perf_counter() - t0
    info_t = task.info()
    files_got = sorted(str(f.relative_to(args.out)) for f in args.out.rglob("*") if f.is_file())
    summary = (
        json.loads((args.out / "summary.json").read_text()) if (args.out / "summary.json").is_file() else {}
    )
    print(
        json.dumps(
            {
                "task": task.uuid,
                "upload_s": round(uploaded, 1),
                "completed_s": round(done, 1),
                "with_download_s": round(total, 1),
                "processing_time_s": round(info_t.processing_time / 1000, 1),
                "registered": summary.get("registered"),
                "images": summary.get("images"),
                "points3D": summary.get("points3D"),
                "frame": summary.get("frame"),
                "assets": {f: (args.out / f).stat().st_size for f in files_got},
            },
            indent=1,
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
