"""Launch the topometric monitor node with config/topometric.yaml."""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch_ros.actions import Node


def generate_launch_description():
    config = os.path.join(get_package_share_directory("topometric_ros"), "config", "topometric.yaml")
    return LaunchDescription([
        Node(package="topometric_ros", executable="topometric_monitor", name="topometric_monitor",
             parameters=[config], output="screen"),
    ])
