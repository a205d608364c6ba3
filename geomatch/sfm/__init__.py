"""Structure-from-Motion around COLMAP: pair planning (and retrieval), the COLMAP database and its
tracks, the view-graph check, mapping, and COLMAP's log and database copies."""

import os

# pairs handled side by side by the per-pair stages before mapping (the view graph's RANSACs,
# track refinement): one thread per core, at most this many
PAIR_THREADS = 4


def pair_threads() -> int:
    """Threads for a per-pair stage whose work releases the GIL (OpenCV, torch kernels)."""
    return max(1, min(PAIR_THREADS, os.cpu_count() or 1))
