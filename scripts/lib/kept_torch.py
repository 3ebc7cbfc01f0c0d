"""Prints the pin ``torch==VERSION`` for the torch this environment already has, if pyproject.toml
allows it; prints nothing otherwise (no torch, or one outside pyproject.toml's range).

scripts/setup.sh adds the pin to pip's constraints so that neither the lock nor an eager upgrade
swaps a build someone chose (CUDA or CPU) for PyPI's default. The version is the installed
distribution's, as pip resolves it, not ``torch.__version__``: PyPI's default build says
``2.14.1+cu130`` there but is distribution ``2.14.1``, and pinning the former makes pip's
resolution impossible.
"""

import re
import sys
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

PYPROJECT = Path(__file__).resolve().parents[2] / "pyproject.toml"


def allowed_torch() -> tuple[tuple[int, int], int]:
    """pyproject.toml's ``"torch>=MAJOR.MINOR,<NEXT_MAJOR"``, read from the file, as (lowest, next major).
    Set-up runs before usl is installed, so the project's own file is where the range lives."""
    spec = re.search(r'"torch>=(\d+)\.(\d+),<(\d+)"', PYPROJECT.read_text())
    if spec is None:
        raise SystemExit(f'{PYPROJECT}: no dependency of the form "torch>=X.Y,<Z"')
    major, minor, below = (int(x) for x in spec.groups())
    return (major, minor), below


def kept_torch_pin() -> str:
    """The constraint line for the installed torch, or "" when there is none to keep."""
    try:
        installed = version("torch")
    except PackageNotFoundError:
        return ""
    lowest, below = allowed_torch()
    major, minor = (int(x) for x in re.match(r"(\d+)\.(\d+)", installed).groups())
    return f"torch=={installed}" if lowest <= (major, minor) and major < below else ""


if __name__ == "__main__":
    sys.stdout.write(kept_torch_pin())
