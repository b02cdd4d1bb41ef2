"""A live web console for a running robot: cameras, joints, loop health and controls, in a browser."""
