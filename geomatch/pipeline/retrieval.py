"""Global image descriptors for ``retrieval:K`` pairing, from the backbones already installed.

No retrieval network (NetVLAD, DINOv2) is available here, so the descriptor is VLAD over the
sparse backbone's local descriptors: a small codebook is fitted on the project's own descriptors
(k-means), each image sums its residuals per visual word, then intra-normalisation, signed
square root and L2 normalisation (Arandjelovic & Zisserman, "All about VLAD"). The local
descriptors come from the same pass the matcher caches, so retrieval costs no extra network run
for the ``sparse``/``geo`` methods.
"""

from __future__ import annotations

import numpy as np


def kmeans(x: np.ndarray, k: int, iterations: int = 20, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    k = min(k, len(x))
    centres = x[rng.choice(len(x), k, replace=False)].copy()
    for _ in range(iterations):
        assign = np.argmax(x @ centres.T, axis=1)  # descriptors are L2-normalised: cosine
        for c in range(k):
            members = x[assign == c]
            if len(members):
                v = members.sum(0)
                centres[c] = v / max(np.linalg.norm(v), 1e-12)
    return centres


def vlad(descriptors: list[np.ndarray], words: int = 32, sample: int = 20000, seed: int = 0) -> np.ndarray:
    """(N, words * D) VLAD vectors of N images' (K_i, D) L2-normalised local descriptors."""
    rng = np.random.default_rng(seed)
    pool = np.concatenate([d for d in descriptors if len(d)]).astype(np.float32)
    if len(pool) > sample:
        pool = pool[rng.choice(len(pool), sample, replace=False)]
    centres = kmeans(pool, words, seed=seed)
    out = np.zeros((len(descriptors), centres.shape[0] * centres.shape[1]), np.float32)
    for i, d in enumerate(descriptors):
        if not len(d):
            continue
        d = d.astype(np.float32)
        assign = np.argmax(d @ centres.T, axis=1)
        v = np.zeros_like(centres)
        np.add.at(v, assign, d - centres[assign])
        v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
        v = v.ravel()
        v = np.sign(v) * np.sqrt(np.abs(v))
        out[i] = v / max(float(np.linalg.norm(v)), 1e-12)
    return out
