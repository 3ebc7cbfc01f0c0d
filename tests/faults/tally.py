"""The fault suite's totals: faults tried, survived, bytes of finished output lost.

Each fault test adds to ``TALLY``; the hooks (registered by the root conftest, so they run in a
pytest-xdist controller too) collect the workers' tallies and print one line at the end.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import pytest


@dataclass
class Tally:
    tried: int = 0
    survived: int = 0
    bytes_lost: int = 0
    sites: set[str] = field(default_factory=set)


TALLY = Tally()


def pytest_sessionfinish(session: pytest.Session) -> None:
    """Under pytest-xdist a worker hands its tally to the controller, which prints the totals."""
    output = getattr(session.config, "workeroutput", None)
    if output is not None:
        output["fault_tally"] = [TALLY.tried, TALLY.survived, TALLY.bytes_lost, sorted(TALLY.sites)]


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node: Any, error: Any) -> None:
    tried, survived, lost, sites = getattr(node, "workeroutput", {}).get("fault_tally", [0, 0, 0, []])
    TALLY.tried, TALLY.survived, TALLY.bytes_lost = (
        TALLY.tried + tried,
        TALLY.survived + survived,
        TALLY.bytes_lost + lost,
    )
    TALLY.sites.update(sites)


def pytest_terminal_summary(terminalreporter: Any) -> None:
    if TALLY.tried:
        terminalreporter.write_line(
            f"faults: {TALLY.tried} tried at {len(TALLY.sites)} write sites, {TALLY.survived} survived, "
            f"{TALLY.bytes_lost} bytes of finished output lost"
        )
