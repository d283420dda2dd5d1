"""Experiments that train and evaluate: the multi-view loss ablation (supplement Tab. 2)."""
