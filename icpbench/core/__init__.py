"""Core types and services: errors, Sample/Batch/Registration, SE(3), the map index and the plugin
registry."""
