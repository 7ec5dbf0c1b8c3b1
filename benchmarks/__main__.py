"""Run benchmarks by name: ``python -m benchmarks`` (all) or ``python -m benchmarks sim``."""
import importlib
import sys

ALL = ["sim", "planes", "metrics", "baselines", "seg", "replay", "fuzz"]

for name in sys.argv[1:] or ALL:
    print(f"== {name}")
    importlib.import_module(f"benchmarks.bench_{name}").main()
