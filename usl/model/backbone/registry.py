"""Name -> builder registries, so configs can pick components by name (detectron2's habit)."""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T", bound=Callable)


class Registry:
    """A named table of builders; ``@REG.register("name")`` adds one, ``REG.get("name")`` finds it."""

    def __init__(self, kind: str):
        self.kind = kind
        self._builders: dict[str, Callable] = {}

    def register(self, name: str | None = None) -> Callable[[T], T]:
        def add(builder: T) -> T:
            key = name or builder.__name__
            if key in self._builders:
                raise KeyError(f"{self.kind} {key!r} is already registered")
            self._builders[key] = builder
            return builder

        return add

    def get(self, name: str) -> Callable:
        if name not in self._builders:
            raise KeyError(f"unknown {self.kind} {name!r}; registered: {sorted(self._builders)}")
        return self._builders[name]

    def names(self) -> list[str]:
        return sorted(self._builders)

    def __contains__(self, name: str) -> bool:
        return name in self._builders


BACKBONES = Registry("backbone")
