"""ROS 2 image subscription backend. ``convert`` is pure Python; ``reader`` needs ``rclpy``."""
