"""Benchmarks: scripts that print figures and write JSON under benchmarks/results/, run as
modules from the repository root (`python -m benchmarks.throughput`). Never part of the tests."""
