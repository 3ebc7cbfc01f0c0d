"""The one build loop every pipeline shares: plan shards, build scenes in parallel, write, resume.

A pipeline supplies an ordered list of ``ShardPlan`` (which scenes go into which shard, fixed by
its arguments alone) and a picklable ``build_scene(unit) -> SceneRecord``. Output is then the same
whatever ``--workers`` is, and a re-run with the same arguments keeps every finished shard.
A ``build_scene`` that writes its rows through ``frame_sink`` streams long scenes via spill files,
so neither the worker nor this process ever holds a whole long scene.
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import sys
import time
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any, Callable, Iterator

from tqdm import tqdm

from usl.cli_common import common_options
from usl.records.encode import SceneRecord
from usl.records.errors import UslError
from usl.records.manifest import build_manifest, dataset_metadata, publish_dataset, usl_version
from usl.records.shards import ShardWriter, remove_stale_temp_files

from .build_state import BuildState
from .spill import init_build_process, set_spill_dir


@dataclass
class ShardPlan:
    split: str
    index: int
    units: list[Any]


@dataclass
class BuildOptions:
    out: Path
    workers: int = 1
    num_shards: int = 1
    shard_index: int = 0
    progress: bool = True


@dataclass
class BuildSummary:
    scenes: int = 0
    frames: int = 0
    kept_shards: int = 0
    built_shards: int = 0
    skipped: int = 0
    seconds: float = 0.0
    manifest_written: bool = False
    pending_shards: list[str] = field(default_factory=list)

    @property
    def frames_per_second(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else 0.0

    def describe(self) -> str:
        text = (
            f"built {self.built_shards} shard(s), kept {self.kept_shards}: {self.scenes} scenes, {self.frames} views "
            f"in {self.seconds:.1f} s ({self.frames_per_second:.2f} views/s), {self.skipped} skipped"
        )
        if self.manifest_written:
            return text + "; manifest.json written"
        return text + f"; manifest not written yet: {len(self.pending_shards)} shard(s) still to build elsewhere"


def build_common_options(seed: str | None = None) -> argparse.ArgumentParser:
    """The parent parser of every pipeline CLI: ``--out``, ``--workers``, ``--quiet`` (and ``--seed``
    with its help, for pipelines that draw random numbers) in usl's shared style."""
    return common_options(out="dataset folder to create or resume", out_required=True,
                          workers="processes building scenes in parallel", seed=seed, quiet="no progress bar")


def add_build_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the build driver itself (with ``build_common_options`` as the parser's parent)."""
    parser.add_argument("--num-shards", type=int, default=1, help="split the build across this many machines")
    parser.add_argument("--shard-index", type=int, default=0, help="which part of --num-shards this run builds")


def build_options_from_args(args: argparse.Namespace) -> BuildOptions:
    if args.workers < 1:
        raise UslError(f"--workers must be >= 1, got {args.workers}")
    if not 0 <= args.shard_index < args.num_shards:
        raise UslError(f"--shard-index must lie in [0, {args.num_shards}), got {args.shard_index}")
    return BuildOptions(args.out, args.workers, args.num_shards, args.shard_index, not args.quiet)


def _jsonable(value: Any) -> Any:
    """Argument values as JSON can store them (paths, also inside lists, become strings)."""
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    return value


def fingerprint_from_args(args: argparse.Namespace) -> dict[str, Any]:
    """Arguments that determine the output: all but the ones that only say how to run."""
    ignored = {"out", "workers", "num_shards", "shard_index", "quiet"}
    return {k: _jsonable(v) for k, v in sorted(vars(args).items()) if k not in ignored}


def creator_from_args(command: str, args: argparse.Namespace) -> dict[str, Any]:
    return {
        "command": command,
        "argv": sys.argv[1:],
        "arguments": {k: _jsonable(v) for k, v in sorted(vars(args).items())},
        "usl_version": usl_version(),
    }


def _scene_stream(
    build_scene: Callable[[Any], SceneRecord], units: list[Any], workers: int, initializer: Callable[[], None]
) -> Iterator[SceneRecord]:
    if workers == 1 or len(units) <= 1:
        initializer()
        yield from map(build_scene, units)
        return
    # spawn: no forked GL contexts, torch thread pools or open file handles in the workers.
    with mp.get_context("spawn").Pool(workers, initializer=initializer) as pool:
        yield from pool.imap(build_scene, units, chunksize=1)


def run_build(
    options: BuildOptions,
    spec: dict[str, Any],
    fingerprint: dict[str, Any],
    plans: list[ShardPlan],
    build_scene: Callable[[Any], SceneRecord],
    creator: dict[str, Any],
    worker_initializer: Callable[[], None] | None = None,
) -> BuildSummary:
    """Build every shard of ``plans`` this run is responsible for, then the manifest if all exist."""
    start = time.perf_counter()
    state = BuildState(options.out, spec["name"], fingerprint)
    state.claim()
    remove_stale_temp_files(options.out)
    state.clear_spills()
    state.spill_dir.mkdir()
    summary = BuildSummary()
    results: dict[tuple[str, int], dict[str, Any]] = {}
    todo: list[ShardPlan] = []
    for position, plan in enumerate(plans):
        done = state.finished(plan.split, plan.index)
        if done is not None:
            results[(plan.split, plan.index)] = done
            summary.kept_shards += 1
        elif position % options.num_shards == options.shard_index:
            todo.append(plan)

    units = [unit for plan in todo for unit in plan.units]
    metadata = dataset_metadata(spec)
    bar = tqdm(total=len(units), desc=f"{spec['name']}: scenes", unit="scene", disable=not options.progress)
    initializer = partial(init_build_process, state.spill_dir, worker_initializer)
    stream = _scene_stream(build_scene, units, options.workers, initializer)
    try:
        for plan in todo:
            with ShardWriter(options.out, plan.split, plan.index, metadata) as writer:
                for _ in plan.units:
                    summary.frames += writer.add_scene(next(stream))
                    summary.scenes += 1
                    bar.update(1)
                result = writer.close()
            results[(plan.split, plan.index)] = state.record(result)
            summary.built_shards += 1
    finally:
        stream.close()  # stops the pool first: no worker writes spills any more
        bar.close()
        set_spill_dir(None)  # the inline path set it in this process
        state.clear_spills()

    summary.pending_shards = [f"{p.split}/{p.index}" for p in plans if (p.split, p.index) not in results]
    finished = list(results.values())
    summary.skipped = sum(s["count"] for r in finished for s in r["skips"])
    if not summary.pending_shards:
        publish_dataset(options.out, build_manifest(spec, finished, creator, state.fingerprint))
        summary.manifest_written = True
    summary.seconds = time.perf_counter() - start
    return summary
