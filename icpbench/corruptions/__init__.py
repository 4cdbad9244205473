"""Realistic lidar corruptions (fog, snow, beam loss, range noise, an occluding vehicle, crosstalk),
graded by severity 1..5; a plugin kind of their own (entry-point group ``icpbench.corruptions``).
The contract is :class:`~icpbench.corruptions.base.Corruption`."""

from icpbench.corruptions.base import SEVERITIES, Corruption, CorruptionRecord, CorruptionResult

__all__ = ["SEVERITIES", "Corruption", "CorruptionRecord", "CorruptionResult"]
