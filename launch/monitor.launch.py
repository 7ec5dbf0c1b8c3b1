"""Launch the topometric monitor node with config/topometric.yaml (and, optionally, the diagnostic aggregator).

    ros2 launch topometric_ros monitor.launch.py use_sim_time:=true points_topic:=/velodyne_points
    ros2 launch topometric_ros monitor.launch.py namespace:=robot1 aggregator:=true config:=/path/to/my.yaml

points_topic / odom_topic and use_sim_time, when given, win over the parameter file (they are passed as
parameters after it); empty (the default) keeps the file's (use_sim_time: false unless the file sets it). The
parameter files' top key is "/**", so they match the nodes under any namespace.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def _true_or_false(context, name: str) -> bool | None:
    """A true/false launch argument; None when empty. Anything else stops the launch before any node starts."""
    text = LaunchConfiguration(name).perform(context).strip().lower()
    if not text:
        return None
    if text not in ("true", "false", "1", "0"):
        raise ValueError(f"{name} must be true or false, got {text!r}")
    return text in ("true", "1")


def _sim_time(context) -> dict:
    """{"use_sim_time": bool} when the argument was given, else {} (the parameter file's value stands)."""
    given = _true_or_false(context, "use_sim_time")
    return {} if given is None else {"use_sim_time": given}


def _nodes(context):
    """The monitor node: the parameter file, then the arguments that were given; and the aggregator."""
    topics = {name: LaunchConfiguration(name).perform(context) for name in ("points_topic", "odom_topic")}
    sim_time = _sim_time(context)
    aggregator = _true_or_false(context, "aggregator")  # checked before any node starts (none left orphaned)
    given = {**{name: value for name, value in topics.items() if value}, **sim_time}
    share = get_package_share_directory("topometric_ros")
    nodes = [Node(package="topometric_ros", executable="topometric_monitor", name="topometric_monitor",
                  namespace=LaunchConfiguration("namespace"), parameters=[LaunchConfiguration("config"), given],
                  output="screen")]
    if aggregator:
        nodes.append(Node(package="diagnostic_aggregator", executable="aggregator_node", name="analyzers",
                          namespace=LaunchConfiguration("namespace"),
                          parameters=[os.path.join(share, "config", "analyzers.yaml"), sim_time], output="screen"))
    return nodes


def generate_launch_description():
    share = get_package_share_directory("topometric_ros")
    return LaunchDescription([
        DeclareLaunchArgument("config", default_value=os.path.join(share, "config", "topometric.yaml"),
                              description="parameter file of the monitor"),
        DeclareLaunchArgument("use_sim_time", default_value="",
                              description="use /clock (bag replay): true or false; empty = the parameter file's"),
        DeclareLaunchArgument("points_topic", default_value="",
                              description="PointCloud2 topic; empty = the parameter file's points_topic"),
        DeclareLaunchArgument("odom_topic", default_value="",
                              description="Odometry topic; empty = the parameter file's odom_topic"),
        DeclareLaunchArgument("namespace", default_value="", description="namespace of the nodes"),
        DeclareLaunchArgument("aggregator", default_value="false",
                              description="true: also start diagnostic_aggregator with config/analyzers.yaml"),
        OpaqueFunction(function=_nodes),
    ])
