"""The end-to-end DIAMOND-SSS pipeline: preliminary reconstruction, diffusion augmentation, final reconstruction."""
