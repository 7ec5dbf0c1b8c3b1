"""Run benchmarks by name: ``python -m benchmarks`` (all but node) or ``python -m benchmarks sim``.

``python -m benchmarks node`` runs the ROS 2 node live; it needs rclpy (source a ROS 2 Jazzy first)."""
import importlib
import sys

ALL = ["sim", "planes", "metrics", "baselines", "seg", "replay", "fuzz", "audit"]

for name in sys.argv[1:] or ALL:
    print(f"== {name}")
    importlib.import_module(f"benchmarks.bench_{name}").main()
