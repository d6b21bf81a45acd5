"""Synthetic scenes at known poses: the triangle (scene, render), the markers, star
fields and ceiling lamps (with an IMU), motion sequences, and the recordings
`visvec simulate` writes (simulate)."""
