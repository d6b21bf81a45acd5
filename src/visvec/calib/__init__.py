"""Calibration: zero-tilt offsets of the triangle rig, camera intrinsics."""
