"""Skills for simulation: scripted experts (which read privileged state) and the ``zero``/``random`` baselines."""
