"""Configuration: the frozen config dataclasses, the run config, the named recipes, the one builder."""
