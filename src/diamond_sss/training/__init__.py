"""Reconstruction: configuration and presets, the training loop, checkpoints, run-level jobs."""
