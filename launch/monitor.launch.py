"""Launch the topometric monitor node with config/topometric.yaml (and, optionally, the diagnostic aggregator).

    ros2 launch topometric_ros monitor.launch.py use_sim_time:=true points_topic:=/velodyne_points
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue


def generate_launch_description():
    share = get_package_share_directory("topometric_ros")
    config = LaunchConfiguration("config")
    use_sim_time = ParameterValue(LaunchConfiguration("use_sim_time"), value_type=bool)
    return LaunchDescription([
        DeclareLaunchArgument("config", default_value=os.path.join(share, "config", "topometric.yaml"),
                              description="parameter file of the monitor"),
        DeclareLaunchArgument("use_sim_time", default_value="false", description="use /clock (bag replay)"),
        DeclareLaunchArgument("points_topic", default_value="/points", description="remap /points to this topic"),
        DeclareLaunchArgument("odom_topic", default_value="/odom", description="remap /odom to this topic"),
        DeclareLaunchArgument("aggregator", default_value="false",
                              description="also start diagnostic_aggregator with config/analyzers.yaml"),
        Node(package="topometric_ros", executable="topometric_monitor", name="topometric_monitor",
             parameters=[config, {"use_sim_time": use_sim_time}],
             # remappings, not parameters: topics set in the YAML stay in force unless these are given
             remappings=[("/points", LaunchConfiguration("points_topic")),
                         ("/odom", LaunchConfiguration("odom_topic"))],
             output="screen"),
        Node(package="diagnostic_aggregator", executable="aggregator_node", name="analyzers",
             parameters=[os.path.join(share, "config", "analyzers.yaml"), {"use_sim_time": use_sim_time}],
             condition=IfCondition(LaunchConfiguration("aggregator")), output="screen"),
    ])
