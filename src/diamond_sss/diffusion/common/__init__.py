"""What the diffusion models share: schedulers, the DDIM loop and pipeline output, EMA, the output cache and its
hashes, the fine-tuning runtime, default paths and the manifest of generated images (import the modules)."""
