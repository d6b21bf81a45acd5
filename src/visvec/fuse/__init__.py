"""Fusion of an IMU with camera fixes.

- inputs: the IMU samples and the fixes, from files or rows;
- model: what the engine asks of a filter; planar and attitude: the two filters;
  gate: the fixes' gate both use;
- replay: the engine (causal replay of late fixes), with history (its samples),
  saturation (a gyro at its range), rest (a rest segment's bias and noise) and align
  (the fixes' clock against the IMU's);
- run: rows from fused samples; live: live sources; camera: a camera pipeline as a
  live source of fixes.
"""
