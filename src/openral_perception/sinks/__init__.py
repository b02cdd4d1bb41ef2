"""Where perception events go: Zenoh (:mod:`.zenoh`, the ``remote`` extra) and ROS 2 (:mod:`.ros2`, needs rclpy).

Each sink imports its library at the top of its own module; the observer loads one only when a
deployment asks for it.
"""
