"""Finished reconstruction run folders as their readers see them (evaluation, the viewer, export, the pipeline and the
diffusion models' rendered geometry): the configuration and the trained scene, without the training loop."""
