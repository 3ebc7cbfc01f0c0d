"""CPU time per usl-train step of two checkouts side by side: ``count_ops.py --cpu-steps`` run in each
tree in turn (A, B, A, B, ...), one thread, and the ratio A / B of each round's medians.

    git worktree add --detach /tmp/base BASE_COMMIT
    python scripts/bench/compare_trees.py /tmp/base . --rounds 3 -- --config tiny --cpu-steps 12
    python scripts/bench/compare_trees.py /tmp/base . -- --config hypersim --objects 20 --cpu-steps 4

Each run is a fresh process (``PYTHONPATH`` = its tree, ``OMP_NUM_THREADS=1``), so compilation and
caches of one tree never serve the other; the CPU time is the process time of the uncounted steps,
which a busy machine inflates less than wall time. Alternating rounds spread slow phases of a shared
machine over both trees. Also prints each tree's op and host-sync counts (the first round's).
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
from pathlib import Path

_CPU = re.compile(r"CPU seconds/step \(median of \d+, 1 thread\): ([0-9.]+)")


def run_tree(tree: Path, count_ops_args: list[str]) -> tuple[float, str]:
    """(CPU seconds per step, the counts line) of ``count_ops.py`` in ``tree``."""
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1"}
    result = subprocess.run(
        [sys.executable, "scripts/bench/count_ops.py", *count_ops_args],
        cwd=tree,
        env=env,
        capture_output=True,
        text=True,
    )
    match = _CPU.search(result.stdout)
    if result.returncode != 0 or match is None:
        raise SystemExit(
            f"compare_trees: count_ops.py failed in {tree}:\n{result.stdout[-2000:]}{result.stderr[-2000:]}"
        )
    counts = next(line for line in result.stdout.splitlines() if line.startswith("ATen ops:"))
    return float(match.group(1)), counts


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("a", type=Path, help="first checkout (e.g. the base commit's worktree)")
    p.add_argument("b", type=Path, help="second checkout (e.g. this one: .)")
    p.add_argument("--rounds", type=int, default=3, help="A, B pairs run")
    p.epilog = "after --: count_ops.py's arguments, --cpu-steps N included"
    argv = sys.argv[1:]
    split = argv.index("--") if "--" in argv else len(argv)
    args = p.parse_args(argv[:split])
    args.count_ops_args = argv[split + 1 :]
    if not any(a.startswith("--cpu-steps") for a in args.count_ops_args):
        p.error("pass count_ops.py's --cpu-steps N after --")
    trees = [args.a.resolve(), args.b.resolve()]
    for tree in trees:
        if not (tree / "scripts/bench/count_ops.py").is_file():
            p.error(f"{tree} is not a checkout of this repository (no scripts/bench/count_ops.py)")
    seconds: dict[Path, list[float]] = {tree: [] for tree in trees}
    ratios = []
    for round_index in range(args.rounds):
        for tree in trees:
            cpu, counts = run_tree(tree, args.count_ops_args)
            if round_index == 0:
                print(f"{tree}: {counts}")
            seconds[tree].append(cpu)
        ratios.append(seconds[trees[0]][-1] / seconds[trees[1]][-1])
        print(
            f"round {round_index + 1}: A {seconds[trees[0]][-1]:.3f} s  B {seconds[trees[1]][-1]:.3f} s  A/B {ratios[-1]:.2f}"
        )
    print(
        f"median CPU s/step: A {statistics.median(seconds[trees[0]]):.3f}  B {statistics.median(seconds[trees[1]]):.3f}"
        f"  A/B {statistics.median(ratios):.2f} (rounds {min(ratios):.2f}..{max(ratios):.2f})"
    )


if __name__ == "__main__":
    main()
