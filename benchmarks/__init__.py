"""Speed benchmarks: medians of repeats, side by side in one run. ``python -m benchmarks [name ...]``."""
import os

# One BLAS thread, set before any benchmark imports numpy: common.single_core() pins the process to one CPU
# afterwards, and OpenBLAS threads started for every CPU would then share that one core.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
