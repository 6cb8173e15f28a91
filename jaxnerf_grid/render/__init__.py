"""Rendering a trained run: views in chunks, fly-around videos, point clouds from rendered depth."""
