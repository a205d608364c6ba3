"""Epipolar geometry of two views: Sampson distances and fundamental matrices (geometry.py;
MAGSAC++ on the host), and the same RANSAC on the tensors' own device (robust_f.py). Used by the
backbones' refinement, by matching and by the database write."""
