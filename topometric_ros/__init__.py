"""topometric_ros: drift alarms for LiDAR SLAM without ground truth (PNE and CPV over a window of scans).

The public facade. Core modules take numpy arrays and 4×4 poses, never ROS messages; node.py alone
imports rclpy. Names are resolved lazily so ``import topometric_ros`` stays light.
"""
from __future__ import annotations

from ._lazy import lazy_exports

__version__ = "0.1.0"

#: public name -> module that defines it
_EXPORTS = {
    "Frame": "window",
    "WindowResult": "pipeline",
    "evaluate_window": "pipeline",
    "Monitor": "monitor",
    "load_config": "config",
}


__getattr__, __all__ = lazy_exports(__name__, _EXPORTS)
