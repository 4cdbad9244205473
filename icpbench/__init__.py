"""icpbench: worst-case error of lidar ICP localisation under corrupted scans.

Reproduces and extends Zhang, Laconte, Lisus, Barfoot, "Prepared for the Worst: A Learning-Based
Adversarial Attack for Resilience Analysis of the ICP Algorithm", ICRA 2025 (arXiv 2403.05666).
"""

from icpbench.core.errors import IcpbenchError, InputError

__all__ = ["Batch", "IcpbenchError", "InputError", "Registration", "Sample", "__version__"]

#: Names loaded on first use (``__version__`` too): the types import torch, which takes a second or
#: more, and the command line installs its Ctrl-C / SIGTERM handlers only once this package is
#: imported (icpbench.cli).
_LAZY = {"Batch", "Registration", "Sample"}


def __getattr__(name: str) -> object:
    if name == "__version__":  # read from the installed metadata on first use (it is slow)
        from importlib.metadata import PackageNotFoundError, version

        try:
            return version("icpbench")
        except PackageNotFoundError:  # running from a source tree that was not installed
            return "0.0.0+unknown"
    if name in _LAZY:
        from icpbench.core import types

        return getattr(types, name)
    raise AttributeError(f"module 'icpbench' has no attribute {name!r}")
