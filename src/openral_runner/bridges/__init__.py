"""Bridges from the tick stream to outside tools (Foxglove, ...). Each imports its library only when selected."""
