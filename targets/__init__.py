"""ICP target plugins (the ICP variants under attack). Installed as ``icpbench.targets``."""
