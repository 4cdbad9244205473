"""Integrity monitor plugins (checks a localisation stack runs on each registration before it trusts
the pose). Installed as ``icpbench.monitors``; the contract is :class:`~icpbench.monitors.base.Monitor`,
its input :class:`~icpbench.monitors.inputs.MonitorInput`."""
