"""Synthetic scenes: rendering of the rig's target at known attitudes."""
