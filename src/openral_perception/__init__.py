"""Perception beside the policy: event detectors on the camera frames, their publisher and sinks, and more eyes.

* :mod:`~openral_perception.observer`: the ``perception`` observer (``observers: [{id: perception}]``),
  which hands each tick's frames to a :class:`~openral_perception.publisher.PerceptionEventPublisher`.
* :mod:`~openral_perception.detectors`: what finds events (motion, scene change, ONNX objects),
  found through the ``openral.detectors`` entry-point group like every other plugin.
* :mod:`~openral_perception.sinks`: where events go (Zenoh, ROS 2).
* :mod:`~openral_perception.reward`: the reward monitor; :mod:`~openral_perception.world_cloud`:
  the world around the robot as a picture. Both are libraries: no deployment field builds them.

Three doors run detectors, each for its own case:

1. ``observers: [{id: perception, ...}]``: any camera backend. Detectors look at the frames the
   runner already read for each tick (at most one per camera per tick) and events are published.
2. ``backend_params.perception`` of a ``gstreamer`` sensor with ``enable_event_tee``: detectors on
   the camera's own event leg, at the leg's rate and whether or not a tick reads the frame, with the
   same publisher and sinks.
3. :class:`~openral_runner.backends.gstreamer.detector_runner.DetectorRunner` (the specification's
   path): no deployment field; code that holds a GStreamer pipeline attaches one ``kind: detector``
   manifest to its tee at run time and receives each detection by callback, with no publisher.

Importing this package loads nothing heavy: numpy only where a module needs it, and onnxruntime,
zenoh or rclpy only in the one module that uses each, when a deployment selects it.
"""
