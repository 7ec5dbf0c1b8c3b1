"""Speed benchmarks: medians of repeats, side by side in one run. ``python -m benchmarks [name ...]``."""
