"""Benchmark scripts (speed is measured here, never asserted in tests)."""
