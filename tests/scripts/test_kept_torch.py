"""scripts/lib/kept_torch.py: the pin with which scripts/setup.sh keeps an installed torch, checked
by pip itself: with the pin as a constraint, pip must find the installed torch satisfies usl's
requirement without looking at any index (PyPI's default build reports ``torch.__version__`` with a
``+cu…`` tag that its distribution's version lacks, and a pin of that made set-up fail)."""

import importlib.util
import os
import re
import subprocess
import sys
from importlib.metadata import PackageNotFoundError, requires, version
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "lib" / "kept_torch.py"
SPEC = importlib.util.spec_from_file_location("kept_torch", SCRIPT)
kept_torch = importlib.util.module_from_spec(SPEC)
SPEC.loader.exec_module(kept_torch)
# usl's own requirement on torch, as the build backend wrote it into the installed metadata
USL_TORCH = next(r for r in requires("usl") if re.match(r"torch\s*[<>=]", r))


def test_the_pin_names_the_installed_distribution_and_pip_accepts_it(tmp_path):
    pin = subprocess.run([sys.executable, str(SCRIPT)], capture_output=True, text=True, check=True).stdout
    assert pin == f"torch=={version('torch')}"
    constraints = tmp_path / "constraints.txt"
    constraints.write_text(pin + "\n")
    # pip as a user's machine has it: none of this machine's pip configuration (a cap on torch, say)
    env = {key: value for key, value in os.environ.items() if not key.startswith("PIP_")}
    resolved = subprocess.run(
        [sys.executable, "-m", "pip", "install", "--dry-run", "--no-index", "--no-deps", "-c", str(constraints)]
        + [USL_TORCH],
        capture_output=True,
        text=True,
        env={**env, "PIP_CONFIG_FILE": os.devnull},
    )
    assert resolved.returncode == 0, resolved.stdout + resolved.stderr
    assert "already satisfied" in resolved.stdout and "Would install" not in resolved.stdout, resolved.stdout


@pytest.mark.parametrize(
    ("installed", "pin"),
    [("2.13.0", "torch==2.13.0"), ("2.14.1+cpu", "torch==2.14.1+cpu"), ("2.12.1", ""), ("3.0.0", "")],
)
def test_only_a_torch_that_pyproject_allows_is_kept(monkeypatch, installed, pin):
    monkeypatch.setattr(kept_torch, "version", lambda name: installed)
    assert kept_torch.kept_torch_pin() == pin


def test_the_range_is_usl_s_own():
    """The range read from pyproject.toml is the one the installed usl declares."""
    (major, minor), below = kept_torch.allowed_torch()
    assert sorted(USL_TORCH.replace("torch", "").replace(" ", "").split(",")) == [f"<{below}", f">={major}.{minor}"]


def test_no_torch_no_pin(monkeypatch):
    def missing(name: str) -> str:
        raise PackageNotFoundError(name)

    monkeypatch.setattr(kept_torch, "version", missing)
    assert kept_torch.kept_torch_pin() == ""
