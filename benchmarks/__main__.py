"""Run benchmarks by name: ``python -m benchmarks`` (ALL) or ``python -m benchmarks sensors sim``; ``--help``
lists them. Each writes out/bench/<name>.json (TOPOMETRIC_BENCH_OUT: another folder) with the machine.

``python -m benchmarks node`` runs the ROS 2 node live; it needs rclpy (source a ROS 2 Jazzy first)."""
import ast
import importlib
import sys
from pathlib import Path

#: Run by a bare ``python -m benchmarks`` (``make bench``): all but node (ROS 2) and sensors (minutes per sensor).
ALL = ["sim", "planes", "metrics", "baselines", "seg", "replay", "fuzz", "audit"]
HERE = Path(__file__).parent


def available() -> dict[str, str]:
    """{name: the first line of its module docstring} of every benchmarks/bench_<name>.py."""
    out = {}
    for f in sorted(HERE.glob("bench_*.py")):
        doc = ast.get_docstring(ast.parse(f.read_text())) or ""
        out[f.stem.removeprefix("bench_")] = doc.splitlines()[0] if doc else ""
    return out


def main(argv: list[str]) -> int:
    names = available()
    if any(a in ("-h", "--help") for a in argv) or any(a not in names for a in argv):
        unknown = [a for a in argv if a not in names and a not in ("-h", "--help")]
        if unknown:
            print(f"error: no benchmark named {', '.join(unknown)}", file=sys.stderr)
        print(__doc__.split("\n\n")[0] + "\n")
        for name, what in names.items():
            print(f"  {name:10s} {what}{'' if name in ALL else '  (not in the default set)'}")
        return 2 if unknown else 0
    for name in argv or ALL:
        print(f"== {name}")
        importlib.import_module(f"benchmarks.bench_{name}").main()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
