"""Benchmarks: one module per topic, run from the repo root as `python -m bench.<name> [--json]`.

Figures and the commands that produced them are recorded in BENCHMARKS.md.
"""
