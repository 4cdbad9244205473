"""Exception types. Library code raises these; only the CLI turns them into exit codes."""


class IcpbenchError(Exception):
    """Base class of every error icpbench raises on purpose."""


class InputError(IcpbenchError, ValueError):
    """Bad user input (a scan, map, file, name or setting); the message says what to fix."""


class PluginUnavailableError(IcpbenchError, ImportError):
    """A registered plugin could not be loaded (usually an optional dependency is missing)."""


class CheckpointError(IcpbenchError, ValueError):
    """A generator checkpoint is missing, corrupt, or does not match the architecture."""
