"""The relightable scene (the model: Gaussians, SSS MLP, light scale) and its file I/O.

It composes rasterization (:mod:`diamond_sss.rendering`) and deferred shading (:mod:`diamond_sss.shading`),
so it sits above both; training, evaluation, the viewer and export build on it.
"""
