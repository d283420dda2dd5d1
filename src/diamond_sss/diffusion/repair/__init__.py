"""Render repair (issue 59, beyond the paper): a one-step image-to-image model that turns the preliminary
reconstruction's render at a target camera and light into the object's image there.

Its input is the render's G-buffer (RGB, alpha, depth, normals, n.l), the nearest real image under the same light
forward-warped into the target with the render's depth, and the target light's code (:mod:`.inputs`); its output
the image (:mod:`.model`). It is trained on the project's own sparse reconstructions rendered at the lattice
images they did not see (:mod:`.data`, :mod:`.train`) and used by ``diamond-sss run --augment repair``
(:mod:`.pipeline`).
"""
