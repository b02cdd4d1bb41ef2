"""Simulation: ``SimRunner`` (one env step per tick), scene files, environment adapters, expert skills, evaluation."""
