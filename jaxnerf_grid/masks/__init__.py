"""The transient foreground: the DPT, masks and training weights, and the photometric evidence."""
