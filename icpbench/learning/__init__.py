"""The learned attack: PointNet++ generator (Zhang et al. 2025, §III-B) and its training."""
