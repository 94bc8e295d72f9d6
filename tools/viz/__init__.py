"""Seeing what was learned: rerun scenes, segmentation plots, MCAP logs of policy runs."""
