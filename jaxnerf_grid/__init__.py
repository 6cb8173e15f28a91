"""jaxnerf-grid: foreground-excluded NeRF for power-grid towers, in functional JAX."""

__version__ = "0.1.0"
