"""Launch the topometric monitor node with config/topometric.yaml (and, optionally, the diagnostic aggregator).

    ros2 launch topometric_ros monitor.launch.py use_sim_time:=true points_topic:=/velodyne_points
    ros2 launch topometric_ros monitor.launch.py namespace:=robot1 aggregator:=true config:=/path/to/my.yaml

points_topic / odom_topic, when given, win over the parameter file (they are passed as parameters after
it); empty (the default) keeps the file's. The parameter files' top key is "/**", so they match the
nodes under any namespace.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue


def _monitor(context):
    """The monitor node: the parameter file, use_sim_time, then the topic arguments that were given."""
    topics = {name: LaunchConfiguration(name).perform(context) for name in ("points_topic", "odom_topic")}
    params = [LaunchConfiguration("config"),
              {"use_sim_time": ParameterValue(LaunchConfiguration("use_sim_time"), value_type=bool)}]
    given = {name: value for name, value in topics.items() if value}
    if given:
        params.append(given)
    return [Node(package="topometric_ros", executable="topometric_monitor", name="topometric_monitor",
                 namespace=LaunchConfiguration("namespace"), parameters=params, output="screen")]


def generate_launch_description():
    share = get_package_share_directory("topometric_ros")
    use_sim_time = ParameterValue(LaunchConfiguration("use_sim_time"), value_type=bool)
    return LaunchDescription([
        DeclareLaunchArgument("config", default_value=os.path.join(share, "config", "topometric.yaml"),
                              description="parameter file of the monitor"),
        DeclareLaunchArgument("use_sim_time", default_value="false", description="use /clock (bag replay)"),
        DeclareLaunchArgument("points_topic", default_value="",
                              description="PointCloud2 topic; empty = the parameter file's points_topic"),
        DeclareLaunchArgument("odom_topic", default_value="",
                              description="Odometry topic; empty = the parameter file's odom_topic"),
        DeclareLaunchArgument("namespace", default_value="", description="namespace of the nodes"),
        DeclareLaunchArgument("aggregator", default_value="false",
                              description="also start diagnostic_aggregator with config/analyzers.yaml"),
        OpaqueFunction(function=_monitor),
        Node(package="diagnostic_aggregator", executable="aggregator_node", name="analyzers",
             namespace=LaunchConfiguration("namespace"),
             parameters=[os.path.join(share, "config", "analyzers.yaml"), {"use_sim_time": use_sim_time}],
             condition=IfCondition(LaunchConfiguration("aggregator")), output="screen"),
    ])
