"""Attack plugins (perturb scans within a budget). Installed as ``icpbench.attacks``."""
