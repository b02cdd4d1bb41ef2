"""Perception beside the policy: event detectors on the camera frames, their publisher and sinks, and more eyes.

* :mod:`~openral_perception.observer`: the ``perception`` observer (``observers: [{id: perception}]``),
  which hands each tick's frames to a :class:`~openral_perception.publisher.PerceptionEventPublisher`.
* :mod:`~openral_perception.detectors`: what finds events (motion, scene change, ONNX objects),
  found through the ``openral.detectors`` entry-point group like every other plugin.
* :mod:`~openral_perception.sinks`: where events go (Zenoh, ROS 2).
* :mod:`~openral_perception.reward`: the reward monitor; :mod:`~openral_perception.world_cloud`:
  the world around the robot as a picture.

Importing this package loads nothing heavy: numpy only where a module needs it, and onnxruntime,
zenoh or rclpy only in the one module that uses each, when a deployment selects it.
"""
