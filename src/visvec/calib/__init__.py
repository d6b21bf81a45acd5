"""Calibrations: the camera's intrinsics from chessboards (camera), the triangle rig's
zero-tilt offsets and yaw zero (zero_tilt), a rolling shutter's readout (readout), the
markers rig's self-calibration (system); tomlout writes their files."""
