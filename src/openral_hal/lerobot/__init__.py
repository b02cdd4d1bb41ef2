"""LeRobot's devices under openral: its robots as HALs, its unit conventions, its third-party plugins.

Everything that imports ``lerobot`` does it inside a function, so the default install (no
``lerobot`` extra) imports this package without it.
"""
