"""Where build workers spill the frame rows of long scenes, and the sink pipelines write them to.

``run_build`` tells every worker process (and, with one worker, its own process) the spill folder
and its own temp-file token through the executor's initializer; ``build_scene`` functions then only
call ``frame_sink(scene_id)`` and need not know whether they run inside a build, in which process,
or how long the scene will be.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from usl.records.shards import FrameSink
from usl.records.tempfiles import set_process_token

_spill_dir: Path | None = None  # set per process by run_build; None outside a build


def frame_sink(scene_id: str) -> FrameSink:
    """A sink for one scene's frame rows, in order of view_id::

        with frame_sink(scene_id) as sink:
            for ...:
                sink.add(frame_row(...))
            return sink.finish(objects, skips)

    Inside a build a long scene is spilled to disk (the record names the file); outside one
    (tests, benchmarks calling ``build_scene`` directly, Ray tasks) the record holds its rows.
    """
    return FrameSink(scene_id, _spill_dir)


def set_spill_dir(path: Path | None) -> None:
    global _spill_dir
    _spill_dir = path


def init_build_process(spill_dir: Path | None, token: str, initializer: Callable[[], None] | None) -> None:
    """Executor initializer: spill folder and the driver's temp-file token, then the pipeline's own."""
    set_spill_dir(spill_dir)
    set_process_token(token)
    if initializer is not None:
        initializer()
