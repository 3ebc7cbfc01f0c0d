"""The one build loop every pipeline shares: plan shards, build scenes in parallel, write, resume.

A pipeline supplies an ordered list of ``ShardPlan`` (which scenes go into which shard, fixed by
its arguments alone) and a picklable ``build_scene(unit) -> SceneRecord``. Output is then the same
whatever ``--workers`` or ``--executor`` is, and a re-run with the same arguments keeps every
finished shard. Any number of runs may share one ``--out`` (``usl.records.claims``): each claims
a shard before building it, and whichever finishes the last shard writes the manifest.
A ``build_scene`` that writes its rows through ``frame_sink`` streams long scenes via spill files,
so neither the worker nor this process ever holds a whole long scene.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Generator, Iterator
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

from tqdm import tqdm

from usl.cli.common import common_options
from usl.errors import UslError, one_line
from usl.records.build_state import STATE_DIR, BuildState, shard_name
from usl.records.claims import STALE_AFTER_SECONDS, Owner
from usl.records.encode import SceneRecord, Skip
from usl.records.manifest import build_manifest, dataset_metadata, publish_dataset, usl_version
from usl.records.names import check_name
from usl.records.shards import ShardWriter
from usl.records.storage_faults import storage_faults
from usl.records.tempfiles import process_token

from .executors import EXECUTORS, make_executor, ordered_results
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
    executor: str = "local"
    ray_address: str | None = None
    skip_bad_scenes: bool = False
    claim_timeout: float = STALE_AFTER_SECONDS


@dataclass
class BuildSummary:
    scenes: int = 0
    frames: int = 0
    kept_shards: int = 0
    built_shards: int = 0
    skipped: int = 0
    failed_scenes: int = 0
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
        if self.failed_scenes:
            text += f" ({self.failed_scenes} scene(s) not converted, reasons in the manifest's skips)"
        if self.manifest_written:
            return text + "; manifest.json written"
        return text + (
            f"; manifest not written yet: {len(self.pending_shards)} shard(s) still to build by other "
            "runs on this --out (the last to finish writes it), or re-run to finish them"
        )


def build_common_options(seed: str | None = None) -> argparse.ArgumentParser:
    """The parent parser of every pipeline CLI: ``--out``, ``--workers``, ``--quiet`` (and ``--seed``
    with its help, for pipelines that draw random numbers) in usl's shared style."""
    return common_options(
        out="dataset folder to create or resume",
        out_required=True,
        workers="processes building scenes in parallel",
        seed=seed,
        quiet="no progress bar",
    )


def add_build_arguments(parser: argparse.ArgumentParser, skip_bad_scenes: bool = False) -> None:
    """Options of the build driver itself (with ``build_common_options`` as the parser's parent);
    ``skip_bad_scenes`` is that pipeline's default."""
    parser.add_argument("--num-shards", type=int, default=1, help="split the build across this many machines")
    parser.add_argument("--shard-index", type=int, default=0, help="which part of --num-shards this run builds")
    parser.add_argument(
        "--executor",
        choices=EXECUTORS,
        default="local",
        help="local: this machine (--workers processes); ray: Ray tasks on a cluster, same output",
    )
    parser.add_argument(
        "--ray-address",
        default=None,
        help="Ray cluster to use with --executor ray (e.g. auto, ray://head:10001); "
        "default: start a local Ray instance",
    )
    parser.add_argument(
        "--skip-bad-scenes",
        action=argparse.BooleanOptionalAction,
        default=skip_bad_scenes,
        help="record a scene that fails to convert as a skip (reason in the manifest) and go on",
    )
    parser.add_argument(
        "--claim-timeout",
        type=float,
        default=STALE_AFTER_SECONDS,
        help="seconds without a heartbeat after which another machine's shard claim is taken over",
    )


def build_options_from_args(args: argparse.Namespace) -> BuildOptions:
    if args.workers < 1:
        raise UslError(f"--workers must be >= 1, got {args.workers}")
    if not 0 <= args.shard_index < args.num_shards:
        raise UslError(f"--shard-index must lie in [0, {args.num_shards}), got {args.shard_index}")
    if args.claim_timeout <= 0:
        raise UslError(f"--claim-timeout must be > 0 seconds, got {args.claim_timeout}")
    if args.ray_address is not None and args.executor != "ray":
        raise UslError("--ray-address needs --executor ray")
    return BuildOptions(
        args.out,
        args.workers,
        args.num_shards,
        args.shard_index,
        not args.quiet,
        args.executor,
        args.ray_address,
        args.skip_bad_scenes,
        args.claim_timeout,
    )


# Options that say how to run, not what to build: a run may change them and still resume or join.
RUN_OPTIONS = {
    "out",
    "workers",
    "num_shards",
    "shard_index",
    "quiet",
    "executor",
    "ray_address",
    "skip_bad_scenes",
    "claim_timeout",
    "device",  # where a model runs (usl-convert-scannet --masks model)
    "segment_batch_size",
    "sfm_threads",  # usl-convert-captures --poses sfm
}


def _jsonable(value: Any) -> Any:
    """Argument values as JSON can store them (paths, also inside lists, become strings)."""
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    return value


def fingerprint_from_args(args: argparse.Namespace) -> dict[str, Any]:
    """Arguments that determine the output: all but the ones that only say how to run."""
    return {k: _jsonable(v) for k, v in sorted(vars(args).items()) if k not in RUN_OPTIONS}


def creator_from_args(command: str, args: argparse.Namespace) -> dict[str, Any]:
    return {
        "command": command,
        "argv": sys.argv[1:],
        "arguments": {k: _jsonable(v) for k, v in sorted(vars(args).items())},
        "usl_version": usl_version(),
    }


def scratch_dir(out: Path) -> Path:
    """This process's private working folder inside a build (made by ``run_build``'s ``prepare``,
    removed when the run ends, reaped by a later run if this one is killed)."""
    return Path(out) / STATE_DIR / f"scratch-{process_token()}"


FAILED_SCENE = "scene not converted: "  # reason prefix of a --skip-bad-scenes skip


@dataclass
class BuiltScene:
    record: SceneRecord
    error: str | None = None  # set when the scene failed and was recorded as a skip


@dataclass(frozen=True)
class SceneBuilder:
    """``build_scene`` as the executors run it: with ``skip_bad``, a failing scene becomes a skip."""

    build_scene: Callable[[Any], SceneRecord]
    skip_bad: bool

    def __call__(self, unit: Any) -> BuiltScene:
        if not self.skip_bad:
            return BuiltScene(self.build_scene(unit))
        try:
            return BuiltScene(self.build_scene(unit))
        except Exception as exc:  # any failure of one scene's input; the message says which file
            scene_id = str(getattr(unit, "scene_id", unit))
            error = f"{type(exc).__name__}: {one_line(exc)}" if not isinstance(exc, UslError) else one_line(exc)
            path = str(getattr(unit, "scene_dir", "") or scene_id)
            return BuiltScene(SceneRecord(scene_id, [], skips=[Skip(f"{FAILED_SCENE}{error}", path)]), error)


def _claimed_units(
    todo: list[ShardPlan], owner: Owner, state: BuildState
) -> Iterator[tuple[tuple[ShardPlan, int], Any]]:
    """Units of the shards this run wins the claim of, claimed one shard at a time as they are drawn.

    Shards another live process held are tried once more at the end: it may have died meanwhile.
    """
    held_elsewhere = []
    for plan in todo:
        if not (yield from _units_if_claimed(plan, owner, state)):
            held_elsewhere.append(plan)
    for plan in held_elsewhere:
        yield from _units_if_claimed(plan, owner, state)


def _units_if_claimed(
    plan: ShardPlan, owner: Owner, state: BuildState
) -> Generator[tuple[tuple[ShardPlan, int], Any], None, bool]:
    """The plan's units if this run claims it (returns False if a live process holds the claim)."""
    name = shard_name(plan.split, plan.index)
    if not owner.claim(name, on_takeover=partial(state.remove_temp_files, plan.split, plan.index)):
        return False
    if state.marker(plan.split, plan.index) is not None:
        owner.release(name)  # another process finished it since this run started
        return True
    for position, unit in enumerate(plan.units):
        yield (plan, position), unit
    return True


def run_build(
    options: BuildOptions,
    spec: dict[str, Any],
    fingerprint: dict[str, Any],
    plans: list[ShardPlan],
    build_scene: Callable[[Any], SceneRecord],
    creator: dict[str, Any],
    worker_initializer: Callable[[], None] | None = None,
    prepare: Callable[[], None] | None = None,
) -> BuildSummary:
    """Build every shard of ``plans`` this run is responsible for and can claim, then the manifest
    if all exist. ``prepare`` runs once the folder is known to hold this build (e.g. to fill
    ``scratch_dir``): a run refused for other arguments writes nothing."""
    start = time.perf_counter()
    if any(not plan.units for plan in plans):
        raise ValueError("every ShardPlan needs at least one unit")
    for plan in plans:  # the converters check names where they read them; nothing reaches a path unchecked
        check_name(plan.split, "split", f"{spec['name']} shard plan")
    keys = [(plan.split, plan.index) for plan in plans]
    state = BuildState(options.out, spec["name"], fingerprint, keys, about={"spec": spec, "creator": creator})
    state.check()  # a folder of another build or of other files is refused before anything is written
    with storage_faults(options.out, "the shards finished so far are kept"):
        summary = _build(options, spec, state, plans, build_scene, creator, worker_initializer, prepare)
    summary.seconds = time.perf_counter() - start
    return summary


def _build(
    options: BuildOptions,
    spec: dict[str, Any],
    state: BuildState,
    plans: list[ShardPlan],
    build_scene: Callable[[Any], SceneRecord],
    creator: dict[str, Any],
    worker_initializer: Callable[[], None] | None,
    prepare: Callable[[], None] | None,
) -> BuildSummary:
    summary = BuildSummary()
    keys = [(plan.split, plan.index) for plan in plans]
    with Owner(state.dir, options.claim_timeout, token_dirs=(state.spill_dir,)) as owner:
        created = state.open()
        try:
            if prepare is not None:
                prepare()
        except BaseException:
            if created and not owner.others_alive():
                state.forget()
            raise
        todo = []
        for position, plan in enumerate(plans):
            if state.finished(plan.split, plan.index) is not None:
                summary.kept_shards += 1
            elif position % options.num_shards == options.shard_index:
                todo.append(plan)
        _build_shards(options, spec, state, owner, todo, build_scene, worker_initializer, summary)
        finished = {key: state.marker(*key) for key in keys}
        summary.pending_shards = [f"{split}/{index}" for (split, index), r in finished.items() if r is None]
        results = [r for r in finished.values() if r is not None]
        summary.skipped = sum(s["count"] for r in results for s in r["skips"])
        failed = [s for r in results for s in r["skips"] if s["reason"].startswith(FAILED_SCENE)]
        if failed and not any(r["frames"]["rows"] for r in results):
            raise UslError(
                f"every scene built so far failed to convert or was empty, e.g. {failed[0]['path']}: "
                f"{failed[0]['reason']}; fix the input (the failed scenes are recorded as skips in "
                f"{options.out}: delete it before re-running)"
            )
        if not summary.pending_shards:
            publish_dataset(options.out, build_manifest(spec, results, creator, state.fingerprint))
            summary.manifest_written = True
            if not owner.others_alive():
                _remove_empty(state.spill_dir)
    return summary


def _build_shards(
    options: BuildOptions,
    spec: dict[str, Any],
    state: BuildState,
    owner: Owner,
    todo: list[ShardPlan],
    build_scene: Callable[[Any], SceneRecord],
    worker_initializer: Callable[[], None] | None,
    summary: BuildSummary,
) -> None:
    """Claim, build and commit shards of ``todo`` one after the other, scenes in parallel."""
    metadata = dataset_metadata(spec)
    spill = state.spill_dir if options.executor == "local" else None  # Ray results travel in memory
    initializer = partial(init_build_process, spill, owner.token, worker_initializer)
    builder = SceneBuilder(build_scene, options.skip_bad_scenes)
    bar = tqdm(
        total=sum(len(p.units) for p in todo),
        desc=f"{spec['name']}: scenes",
        unit="scene",
        disable=not options.progress,
    )
    writer: ShardWriter | None = None
    try:
        with make_executor(options.executor, options.workers, options.ray_address, initializer) as executor:
            for (plan, position), built in ordered_results(executor, builder, _claimed_units(todo, owner, state)):
                if position == 0:
                    writer = ShardWriter(options.out, plan.split, plan.index, metadata)
                assert writer is not None
                summary.frames += writer.add_scene(built.record)
                summary.scenes += 1
                if built.error is not None:
                    summary.failed_scenes += 1
                    tqdm.write(f"{spec['name']}: scene {built.record.scene_id} not converted: {built.error}")
                bar.update(1)
                if position == len(plan.units) - 1:
                    state.record(writer.close())
                    writer = None
                    owner.release(shard_name(plan.split, plan.index))
                    summary.built_shards += 1
    finally:
        if writer is not None:
            writer.abort()
        bar.close()
        set_spill_dir(None)  # the inline path set it in this process


def _remove_empty(directory: Path) -> None:
    try:
        directory.rmdir()
    except OSError:  # absent, or another run's spills arrived meanwhile
        pass
