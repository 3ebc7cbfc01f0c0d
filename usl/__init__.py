"""usl: 3D object shape and layout from multi-view 2D masks (CVPR 2022), with dataset pipelines.

``usl.load(run_or_checkpoint)`` gives a model whose ``predict(image)`` returns the 3D objects of an
image (``usl.inference.api``). Importing ``usl`` loads nothing else: torch loads on first use.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"  # the package's version (pyproject.toml reads it from here)
__all__ = ["Model", "Object3D", "Scene", "__version__", "load"]

if TYPE_CHECKING:
    from usl.inference.api import Model, Object3D, Scene, load


def __getattr__(name: str) -> Any:
    if name in ("Model", "Object3D", "Scene", "load"):
        from usl.inference import api

        return getattr(api, name)
    raise AttributeError(f"module 'usl' has no attribute {name!r}")
