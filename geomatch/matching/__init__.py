"""Matching one pair: the matcher, the geometry-aware optimizer and its refinements (least-squares
sub-pixel matching), the quarter-turn probe and the tiling of aerial x ground pairs."""
