"""Matching one pair: the matcher, the geometry-aware optimizer and its refinements, the
quarter-turn probe and the tiling of aerial x ground pairs.

The paper's steps, in the order :meth:`matcher.Matcher.match` runs them, and where each lives:

1. anchors: the detector's keypoints matched by LightGlue (``Matcher._anchors``; the networks
   in geomatch.features, their output cached per pair in featurecache.py); where the anchors
   alone fit an F with ``anchors_suffice`` inliers, that is the answer (``_anchors_suffice``);
2. F from the anchors, the optimizer's starting point, and
3. dense matches re-weighted by their Sampson distance under it, round after round
   (``_dense_matches``: dense.py over optimizer.py);
4. window refinement of the dense cells under the epipolar prior (geomatch.features.refine,
   the dense heads' own step, called from dense.py);
5. merge of the anchors and the dense matches without duplicates (``_merge``: dense.merge_parts);
6. sub-pixel refinement: least-squares matching of the final points (``_subpixel``:
   geomatch.features.subpixel);
7. final check: the final F, the matches far from it dropped, and the anchors' support of it
   (``_final_check``, ``_anchor_support``).

Refinement (4, 6) lives in geomatch.features, below matching: the dense heads refine their own
cells, and geomatch.sfm (ranked beside matching, so it cannot import it) refines tracks with the
same least-squares matching (sfm/trackrefine.py).

Beside the steps: config.py (MatcherConfig, MatchResult), variants.py (the matchers a matcher
derives: ``auto``'s per-pair method, ``light_first``'s light and full matchers), guided.py (the
guided matcher of two aerial photos), rotation.py and probes.py (quarter turns, crop choice),
tiling.py, turnhint.py, stored.py (a matcher over features on disk).
"""
