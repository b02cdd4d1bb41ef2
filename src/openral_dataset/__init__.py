"""Recording: episodes as LeRobotDataset v3.0 (pyarrow + PyAV), committed atomically, checked and replayed."""
