"""Capture backends, one module each; each is an entry point in ``openral.sensor_backends``.

Nothing here imports a backend: the plugin loader imports the one module a deployment selects,
so cv2, gi, mujoco or rclpy load only when that backend is used.
"""
