"""Diffusion models that densify a sparse OLAT capture (relighting, novel views) and their shared utilities."""
