"""Table 1's scores kept in a small folder, so that the table resumes where its output folder is gone.

    python3 scripts/experiments/table1_record.py save runs/table1 docs/results/table1 runs/usl5/seed0 baselines plan.tsv
    python3 scripts/experiments/table1_record.py restore docs/results/table1 runs/table1

``table1.sh --record DIR`` saves each run once it is scored, the baselines, the plan and the table,
and restores before it plans. Table 1 at the recipe's length takes longer than one machine may be
kept; its training runs are the cost, and what the table reads of them is a few kilobytes a run.
The record keeps the output folder's layout with only those files (no checkpoints, no pictures,
no per-object reports, no Markdown reports), so ``table1_summary.py DIR`` writes the same table from it as from the
output folder, and a run recorded there counts as finished in an output folder it is restored into.
"""

from __future__ import annotations

import argparse
import re
import shutil
import sys
from collections.abc import Sequence
from pathlib import Path

# What a finished run's (or the baselines') figures rest on, relative to its folder: the recipe it
# trained, the checkpoint it scored (the pointer only), its CPU time, and usl-eval's reports
# (metrics.json; not table.md, whose links to pictures and training curves the record would break).
RECORDED = (
    "train/config.yaml",
    "train/checkpoints/last_checkpoint",
    "train_time.txt",
    "eval/summary.json",
    "eval/seed*/metrics.json",
    "eval/seed*.time",
)
BUDGET = "budget.txt"
SUMMARY = "eval/summary.json"  # written once every held-out build is scored: the run is finished
_RUN = re.compile(r"^runs/[^/]+/seed\d+$")


def _check_folder(folder: str) -> None:
    if folder != "baselines" and not _RUN.match(folder) and "/" in folder:
        raise ValueError(f"{folder}: not a run (runs/<row>/seed<k>), 'baselines' or a file of the output folder")


def save(out: Path, record: Path, folder: str) -> None:
    """Copy ``out/folder`` into ``record``: a run's or the baselines' recorded files, or one file of
    the output folder (``plan.tsv``, ``table1.md``, ...). A folder is replaced whole: a stop halfway
    leaves the previous record of it (or none), never a mix."""
    _check_folder(folder)
    source, target = out / folder, record / folder
    if source.is_file():
        target.parent.mkdir(parents=True, exist_ok=True)
        partial = target.with_name(target.name + ".partial")
        shutil.copyfile(source, partial)
        partial.replace(target)
        return
    if not (source / SUMMARY).is_file():
        raise ValueError(f"{source}: not scored yet (no {SUMMARY})")
    partial, previous = target.with_name(target.name + ".partial"), target.with_name(target.name + ".previous")
    for leftover in (partial, previous):
        shutil.rmtree(leftover, ignore_errors=True)
    for pattern in RECORDED:
        for path in sorted(source.glob(pattern)):
            copy = partial / path.relative_to(source)
            copy.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(path, copy)
    if target.exists():
        target.replace(previous)
    partial.replace(target)
    shutil.rmtree(previous, ignore_errors=True)


def finished(folder: Path) -> list[str]:
    """The scored runs and baselines under a table's folder, relative to it."""
    summaries = [folder / "baselines" / SUMMARY, *sorted(folder.glob(f"runs/*/*/{SUMMARY}"))]
    names = [str(s.relative_to(folder).parent.parent) for s in summaries if s.is_file()]
    return [n for n in names if n == "baselines" or _RUN.match(n)]


def restore(record: Path, out: Path) -> list[str]:
    """Copy into ``out`` the budget and every scored run or baseline that ``record`` holds and
    ``out`` has not scored; return what was copied. A record of another budget is refused."""
    if not record.is_dir():
        return []
    out.mkdir(parents=True, exist_ok=True)
    budget = record / BUDGET
    if budget.is_file():
        if (out / BUDGET).is_file() and (out / BUDGET).read_text() != budget.read_text():
            raise ValueError(
                f"{out} and {record} hold runs of different budgets (compare their {BUDGET}); give another --out or --record"
            )
        shutil.copyfile(budget, out / BUDGET)
    copied = []
    for folder in finished(record):
        if (out / folder / SUMMARY).is_file():
            continue
        shutil.copytree(record / folder, out / folder, dirs_exist_ok=True)
        copied.append(folder)
    return copied


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser("save", help="copy scored runs, the baselines or files of OUT into RECORD")
    s.add_argument("out", type=Path)
    s.add_argument("record", type=Path)
    s.add_argument("folders", nargs="+", help="runs/<row>/seed<k>, baselines, or a file such as plan.tsv")
    r = sub.add_parser("restore", help="copy into OUT what RECORD holds and OUT lacks")
    r.add_argument("record", type=Path)
    r.add_argument("out", type=Path)
    args = p.parse_args(argv)
    try:
        if args.command == "save":
            for folder in args.folders:
                save(args.out, args.record, folder)
        else:
            for folder in restore(args.record, args.out):
                print(f"table1_record: restored {folder} from {args.record}")
    except (OSError, ValueError) as exc:
        print(f"table1_record: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
