"""icpbench: worst-case error of lidar ICP localisation under corrupted scans.

Reproduces and extends Zhang, Laconte, Lisus, Barfoot, "Prepared for the Worst: A Learning-Based
Adversarial Attack for Resilience Analysis of the ICP Algorithm", ICRA 2025 (arXiv 2403.05666).
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("icpbench")
except PackageNotFoundError:  # running from a source tree that was not installed
    __version__ = "0.0.0+unknown"

from icpbench.core.errors import IcpbenchError, InputError  # noqa: E402
from icpbench.core.types import Batch, Registration, Sample  # noqa: E402

__all__ = ["Batch", "IcpbenchError", "InputError", "Registration", "Sample", "__version__"]
