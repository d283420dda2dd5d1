"""Metrics, figures and reports; evaluating and rendering trained run folders (:mod:`.run`)."""
