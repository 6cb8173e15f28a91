"""Datasets: loaders for transforms.json / Blender / COLMAP / LLFF, preprocessing, synthetic scenes."""
