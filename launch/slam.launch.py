"""ESLAM on a robot: the SLAM node with its parameters, the camera driver's topics, the Fast DDS profile and RViz.

    ros2 launch eslam_ros slam.launch.py camera:=realsense
    ros2 launch eslam_ros slam.launch.py camera:=orbbec odom_frame:=odom base_frame:=base_link rviz:=true
    ros2 launch eslam_ros slam.launch.py camera:=custom rgb_topic:=/cam/rgb depth_topic:=/cam/depth \
        info_topic:=/cam/rgb/camera_info lifecycle:=true

`camera` picks the topics of a common driver (start the driver yourself, with depth registered to colour; see
CAMERAS); `rgb_topic`, `depth_topic`, `info_topic` override them. Every argument in NODE_PARAMETERS left empty keeps
the value of `params_file` (default: the shipped config/slam_node.yaml); a given one overrides it. `lifecycle:=true`
starts the managed node (slam_lifecycle_node): configure and activate it with `ros2 lifecycle set /slam_node
configure` / `activate`, or a lifecycle manager. docs/ros.md ("Robot integration") explains the TF modes.
"""
from pathlib import Path

import yaml
from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction, SetEnvironmentVariable
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import LifecycleNode, Node

# Topics of common RGB-D drivers on Jazzy (rgb, registered depth, colour camera_info); `ros2 topic list` shows yours.
CAMERAS = {
    # realsense2_camera 4.x: ros2 launch realsense2_camera rs_launch.py align_depth.enable:=true
    "realsense": ("/camera/camera/color/image_raw", "/camera/camera/aligned_depth_to_color/image_raw",
                  "/camera/camera/color/camera_info"),
    # OrbbecSDK_ROS2: ros2 launch orbbec_camera <model>.launch.py depth_registration:=true
    "orbbec": ("/camera/color/image_raw", "/camera/depth/image_raw", "/camera/color/camera_info"),
    # zed_wrapper 4.x: ros2 launch zed_wrapper zed_camera.launch.py camera_model:=<model> (depth is 32FC1 metres)
    "zed": ("/zed/zed_node/rgb/image_rect_color", "/zed/zed_node/depth/depth_registered",
            "/zed/zed_node/rgb/camera_info"),
    # Azure_Kinect_ROS_Driver: depth_to_rgb is the depth registered to the colour camera
    "azure_kinect": ("/rgb/image_raw", "/depth_to_rgb/image_raw", "/rgb/camera_info"),
    # eslam bag write / eslam bag play
    "bag": ("/camera/color/image_raw", "/camera/depth/image_raw", "/camera/color/camera_info"),
}

# Node parameters settable as launch arguments of the same name (empty = keep the params_file value).
NODE_PARAMETERS = (
    "preset", "config_file", "policy", "workers", "output_dir", "input_qos", "map_frame", "odom_frame", "base_frame",
    "odom_source", "base_to_camera", "pose_frame", "publish_tf", "tf_child_frame", "mesh_period", "save_on_shutdown",
    "diagnostics.min_input_rate", "use_sim_time",
)
# ... of which these are strings (launch arguments are text; the others are read as YAML: 2, true, [0.1, 0.0]).
STRING_PARAMETERS = ("preset", "config_file", "policy", "output_dir", "input_qos", "map_frame", "odom_frame",
                     "base_frame", "odom_source", "pose_frame", "tf_child_frame")


def _share(*parts: str) -> str:
    return str(Path(get_package_share_directory("eslam_ros"), *parts))


def _arguments() -> list:
    args = [
        DeclareLaunchArgument("camera", default_value="realsense", choices=[*CAMERAS, "custom"],
                              description="camera driver whose topics to use"),
        DeclareLaunchArgument("rgb_topic", default_value="", description="colour image topic (overrides camera)"),
        DeclareLaunchArgument("depth_topic", default_value="", description="registered depth topic (overrides camera)"),
        DeclareLaunchArgument("info_topic", default_value="", description="colour camera_info topic"),
        DeclareLaunchArgument("odom_topic", default_value="/odom",
                              description="nav_msgs/Odometry input (odom_source topic or auto without tf2_ros)"),
        DeclareLaunchArgument("params_file", default_value=_share("config", "slam_node.yaml"),
                              description="ROS parameter file of the node"),
        DeclareLaunchArgument("lifecycle", default_value="false", description="start the managed (lifecycle) node"),
        DeclareLaunchArgument("rviz", default_value="false", description="start RViz with the shipped config"),
        DeclareLaunchArgument("rviz_config", default_value=_share("rviz", "slam.rviz")),
        DeclareLaunchArgument("fastdds_profile", default_value=_share("config", "fastdds_shm.xml"),
                              description="Fast DDS profile (large shared-memory segment for images); '' = none"),
    ]
    args += [DeclareLaunchArgument(name, default_value="", description=f"node parameter {name} ('' = params_file)")
             for name in NODE_PARAMETERS]
    return args


def _parameter_overrides(context) -> dict:
    overrides = {}
    for name in NODE_PARAMETERS:
        text = LaunchConfiguration(name).perform(context)
        if text != "":
            overrides[name] = text if name in STRING_PARAMETERS else yaml.safe_load(text)
    return overrides


def _slam_node(context) -> list:
    camera = LaunchConfiguration("camera").perform(context)
    topics = CAMERAS.get(camera, ("", "", ""))
    given = [LaunchConfiguration(n).perform(context) for n in ("rgb_topic", "depth_topic", "info_topic")]
    rgb, depth, info = (g or t for g, t in zip(given, topics))
    if not (rgb and depth and info):
        raise RuntimeError("camera:=custom needs rgb_topic, depth_topic and info_topic")
    remappings = [("rgb/image", rgb), ("depth/image", depth), ("rgb/camera_info", info),
                  ("odom", LaunchConfiguration("odom_topic").perform(context))]
    parameters = [LaunchConfiguration("params_file").perform(context), _parameter_overrides(context)]
    lifecycle = LaunchConfiguration("lifecycle").perform(context).lower() in ("true", "1", "yes")
    if lifecycle:
        return [LifecycleNode(package="eslam_ros", executable="slam_lifecycle_node", name="slam_node", namespace="",
                              parameters=parameters, remappings=remappings, output="screen")]
    return [Node(package="eslam_ros", executable="slam_node", name="slam_node", parameters=parameters,
                 remappings=remappings, output="screen")]


def _fastdds_profile(context) -> list:
    profile = LaunchConfiguration("fastdds_profile").perform(context)
    return [SetEnvironmentVariable("FASTRTPS_DEFAULT_PROFILES_FILE", profile)] if profile else []


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription(_arguments() + [
        OpaqueFunction(function=_fastdds_profile),
        OpaqueFunction(function=_slam_node),
        Node(package="rviz2", executable="rviz2", name="rviz2", arguments=["-d", LaunchConfiguration("rviz_config")],
             condition=IfCondition(LaunchConfiguration("rviz")), output="screen"),
    ])
