"""Leaves shared by every stage: file I/O, progress output, output-folder rules, staged swaps, safetensors."""
