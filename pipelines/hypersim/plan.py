"""Which trajectories and frames to convert, and which shard each goes to.

Decided from the arguments, the split CSV and the scene folders alone (never from worker count),
so every machine of a ``--num-shards`` build plans the same shards. All trajectories of one
Hypersim scene go to the same shard; shards hold ``scenes_per_shard`` Hypersim scenes.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

from pipelines.common import ShardPlan
from usl.errors import UslError

from .camera import check_camera_model
from .convert import ConvertOptions, TrajectoryUnit
from .metadata import CameraModel, TrajectorySplit
from .paths import CAMERA_NAME, SCENE_NAME

OFFICIAL_SPLIT_ORDER = ("train", "val", "test")


@dataclass(frozen=True)
class PlanConfig:
    splits: tuple[str, ...] = ()  # empty: every split of the CSV
    cameras: tuple[str, ...] = ()  # empty: every camera
    frame_stride: int = 1  # convert frames whose number is a multiple of this
    blacklist: frozenset[str] = frozenset()  # "ai_VVV_NNN" or "ai_VVV_NNN/cam_XX"
    scenes_per_shard: int = 4


def discover_scenes(inputs: list[Path]) -> dict[str, Path]:
    """Scene name -> folder, from scene folders and/or folders holding scene folders."""
    found: dict[str, Path] = {}
    for given in inputs:
        given = Path(given)
        if not given.is_dir():
            raise UslError(f"{given}: not a folder")
        if SCENE_NAME.match(given.name):
            scenes = [given]
        else:
            scenes = sorted(c for c in given.iterdir() if c.is_dir() and SCENE_NAME.match(c.name))
            if not scenes:
                raise UslError(f"{given}: neither a Hypersim scene folder (ai_VVV_NNN) nor a folder holding any")
        for scene in scenes:
            if scene.name in found and found[scene.name].resolve() != scene.resolve():
                raise UslError(f"scene {scene.name} given twice: {found[scene.name]} and {scene}")
            found[scene.name] = scene
    return dict(sorted(found.items()))


def parse_blacklist(entries: list[str], file: Path | None) -> frozenset[str]:
    """Blacklist entries from the command line and a file (one per line, '#' starts a comment)."""
    items = [(e, "--blacklist") for e in entries]
    if file is not None:
        if not Path(file).is_file():
            raise UslError(f"{file}: blacklist file not found")
        for number, line in enumerate(Path(file).read_text().splitlines(), start=1):
            text = line.split("#", 1)[0].strip()
            if text:
                items.append((text, f"{file}:{number}"))
    for text, where in items:
        scene, _, camera = text.partition("/")
        if not SCENE_NAME.match(scene) or (camera and not CAMERA_NAME.match(camera)):
            raise UslError(f"{where}: blacklist entry {text!r} is not ai_VVV_NNN or ai_VVV_NNN/cam_XX")
    return frozenset(text for text, _ in items)


def _scene_units(
    scene: str,
    folder: Path,
    trajectories: dict[str, TrajectorySplit],
    model: CameraModel,
    options: ConvertOptions,
    config: PlanConfig,
) -> list[TrajectoryUnit]:
    """The trajectory units of one scene; exclusions of whole trajectories ride on its first unit."""
    units: list[TrajectoryUnit] = []
    orphaned: list[tuple[str, str, int]] = []
    for camera, entry in sorted(trajectories.items()):
        if (config.cameras and camera not in config.cameras) or f"{scene}/{camera}" in config.blacklist:
            continue
        planned = []
        for reason, frames in sorted(entry.excluded.items()):
            count = sum(1 for f in frames if f % config.frame_stride == 0)
            if count:
                planned.append((f"official exclusion: {reason}", f"{scene}/{camera}", count))
        frames = tuple(f for f in entry.frames if f % config.frame_stride == 0)
        if not frames:
            orphaned += planned
            continue
        units.append(TrajectoryUnit(scene, camera, str(folder), model, frames, tuple(planned), options))
    if units and orphaned:
        units[0] = replace(units[0], planned_skips=units[0].planned_skips + tuple(orphaned))
    return units


def plan_shards(
    scenes: dict[str, Path],
    split_table: dict[tuple[str, str], TrajectorySplit],
    camera_models: dict[str, CameraModel],
    options: ConvertOptions,
    config: PlanConfig,
    split_csv: Path,
    camera_csv: Path,
) -> tuple[list[ShardPlan], list[str]]:
    """Shard plans in output order, and one note per scene folder that yields nothing."""
    by_scene: dict[str, dict[str, TrajectorySplit]] = {}
    for (scene, camera), entry in split_table.items():
        by_scene.setdefault(scene, {})[camera] = entry
    groups: dict[str, list[list[TrajectoryUnit]]] = {}
    notes = []
    for scene, folder in scenes.items():
        if scene not in camera_models:
            raise UslError(f"{camera_csv}: no camera parameters for scene {scene} ({folder})")
        check_camera_model(camera_models[scene].matrix, f"{camera_csv}: scene {scene}")
        if scene not in by_scene:
            raise UslError(f"{split_csv}: scene {scene} ({folder}) is not listed")
        splits = {e.split for e in by_scene[scene].values() if e.split is not None}
        if len(splits) > 1:
            raise UslError(f"{split_csv}: scene {scene} has trajectories in several splits {sorted(splits)}")
        if not splits:
            notes.append(f"{scene}: every frame is excluded by the official split")
            continue
        split = splits.pop()
        if (config.splits and split not in config.splits) or scene in config.blacklist:
            continue
        units = _scene_units(scene, folder, by_scene[scene], camera_models[scene], options, config)
        if units:
            groups.setdefault(split, []).append(units)
        else:
            notes.append(f"{scene}: no trajectory or frame left after --cameras, --blacklist, --stride")
    order = [s for s in OFFICIAL_SPLIT_ORDER if s in groups] + sorted(set(groups) - set(OFFICIAL_SPLIT_ORDER))
    plans = []
    for split in order:
        scene_groups = groups[split]
        for index, start in enumerate(range(0, len(scene_groups), config.scenes_per_shard)):
            chunk = scene_groups[start : start + config.scenes_per_shard]
            plans.append(ShardPlan(split, index, [unit for units in chunk for unit in units]))
    return plans, notes
