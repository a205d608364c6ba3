"""Synthetic data with exact ground truth: aerial + ground scenes, indoor rooms, the look-alike
twin scene, and warped package photos."""
