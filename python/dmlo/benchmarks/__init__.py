"""Benchmark scripts: speed as ratios against peers measured in the same run, never timed assertions."""
