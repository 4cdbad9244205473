"""Datasets: procedural objects, mesh folders, the simulated lidar town, KITTI and Boreas."""
