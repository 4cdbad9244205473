"""Example third-party plugin package for icpbench (see the README section "Write your own plugin")."""
