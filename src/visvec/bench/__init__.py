"""Helpers for the benchmark scripts in benchmarks/ (Monte Carlo over rendered frames)."""
