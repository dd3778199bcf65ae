"""Benchmarks behind ``lapreco bench ...``: figures for docs/benchmarks.md, never timed unit tests."""
