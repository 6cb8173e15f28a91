"""Training: the loop and its pool of rays, optimiser, checkpoints, device and host parallelism, run folders."""
