"""SO-100 / SO-101 follower arms on a Feetech STS3215 servo bus.

``protocol`` (packet framing, checksum, control table) and ``calibration`` are pure Python;
``bus`` and ``hal`` import pyserial (the ``serial`` extra) and are loaded only by the plugin
loader when a deployment selects the ``so10x_follower`` adapter. ``emulator`` serves the same
protocol on a pseudo-terminal for tests and demos without an arm.
"""
