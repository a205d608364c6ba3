"""Judging results against ground truth: models (pose AUC, cameras correct after a robust
alignment, wrong verified pairs) and matches (relative pose, homography errors)."""
