"""Evaluation of a trained run: image metrics, LPIPS, tower geometry."""
