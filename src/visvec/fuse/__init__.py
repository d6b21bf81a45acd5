"""Fusion of an IMU with camera fixes: the inputs (inputs), the filters (models), the
causal replay of late fixes (replay, run), live sources (live) and a camera pipeline
as a live source of fixes (camera)."""
