"""Analyses on top of the harness: the analytic sector maths, danger maps, the object study,
dataset pictures and plotting helpers."""
