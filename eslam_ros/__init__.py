"""ROS 2 front end of ESLAM: a thin rclpy node and bag tools over eslam_core."""
