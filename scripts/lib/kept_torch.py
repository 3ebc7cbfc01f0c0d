"""Prints the pin ``torch==VERSION`` for the torch this environment already has, if pyproject.toml
allows it (2.13 or newer, below 3); prints nothing otherwise (no torch, or one outside the range).

scripts/setup.sh adds the pin to pip's constraints so that neither the lock nor an eager upgrade
swaps a build someone chose (CUDA or CPU) for PyPI's default. The version is the installed
distribution's, as pip resolves it, not ``torch.__version__``: PyPI's default build says
``2.14.1+cu130`` there but is distribution ``2.14.1``, and pinning the former makes pip's
resolution impossible.
"""

import re
import sys
from importlib.metadata import PackageNotFoundError, version


def kept_torch_pin() -> str:
    """The constraint line for the installed torch, or "" when there is none to keep."""
    try:
        installed = version("torch")
    except PackageNotFoundError:
        return ""
    major, minor = (int(x) for x in re.match(r"(\d+)\.(\d+)", installed).groups())
    return f"torch=={installed}" if (2, 13) <= (major, minor) < (3, 0) else ""


if __name__ == "__main__":
    sys.stdout.write(kept_torch_pin())
