"""Who is building what in a shared output folder: owners with heartbeats, and shard claims.

Any number of processes, on one machine or many (one shared disk), may run the same build on one
folder. Each registers an *owner* file ``.build/owners/<token>.json`` (host, pid, start time) and,
before building a shard, claims it by creating ``.build/claims/<shard>.json`` with ``O_EXCL``: of
all processes creating the file, exactly one succeeds, on local disks and NFS alike. A daemon
thread touches the owner file and the held claims every few seconds; their mtime is the heartbeat.

A claim or owner is *stale* when its process is gone: on the same host (hostname, boot id and pid
namespace all equal) as soon as its pid no longer exists, elsewhere once its heartbeat is older
than ``stale_after`` seconds. A stale claim is taken over; a stale owner's temp files, spills and
scratch folder are removed. Nothing else is ever deleted, so a live process never loses a file.
Claims make the work disjoint; correctness does not rest on them alone: a shard is a function of
the build's arguments and appears by atomic rename, so even one built twice (a takeover racing a
late heartbeat) is the same file.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from functools import cache
from pathlib import Path
from typing import Any

from usl.errors import UslError

from .tempfiles import process_token, temp_files_of

HEARTBEAT_SECONDS = 5.0
STALE_AFTER_SECONDS = 300.0
_FOLDER_RACE_RETRIES = 100  # each retry needs another process to remove the folder again: it ends fast


@cache
def host_identity() -> str:
    """Processes with equal identities see the same pids (same kernel boot and pid namespace)."""
    parts = [socket.gethostname()]
    try:
        parts.append(Path("/proc/sys/kernel/random/boot_id").read_text().strip())
        parts.append(os.readlink("/proc/self/ns/pid"))
    except OSError:  # not Linux: pids are comparable only by timeout
        parts.append(f"no-boot-id-{os.getpid()}")
    return "|".join(parts)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return True


def _create_exclusive(path: Path, data: dict[str, Any]) -> None:
    """Create ``path`` holding ``data``; FileExistsError if it exists (the atomic claim).

    Its folder is made when missing, again and again if need be: a sole writer that is finishing
    removes the lock folders it leaves empty, and may do so between our mkdir and our create.
    """
    for _ in range(_FOLDER_RACE_RETRIES):
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            break
        except FileNotFoundError:
            with suppress(FileExistsError, FileNotFoundError):  # another process made or removed a folder meanwhile
                path.parent.mkdir(parents=True)
    else:
        fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)  # a real error: let it say so
    with os.fdopen(fd, "w") as f:
        f.write(json.dumps(data))


def _read(path: Path) -> tuple[bytes, float] | None:
    """Raw content and mtime of a claim/owner file, None if it is gone."""
    try:
        return path.read_bytes(), path.stat().st_mtime
    except FileNotFoundError:
        return None


def _holder(raw: bytes) -> dict[str, Any]:
    try:
        data = json.loads(raw)
    except ValueError:  # being written right now (create and write are two steps)
        return {}
    return data if isinstance(data, dict) else {}


def is_stale(raw: bytes, mtime: float, stale_after: float) -> bool:
    """Whether the process that wrote this owner/claim file is gone."""
    if time.time() - mtime > stale_after:
        return True
    holder = _holder(raw)
    if holder.get("host") == host_identity() and holder.get("token") != process_token():
        return not _pid_alive(int(holder["pid"]))
    return False


class Owner:
    """This process's presence in a build folder (a context manager): heartbeat, claims, reaping."""

    def __init__(
        self,
        state_dir: Path,
        stale_after: float = STALE_AFTER_SECONDS,
        heartbeat: float = HEARTBEAT_SECONDS,
        token_dirs: tuple[Path, ...] = (),
    ):
        self.dir = Path(state_dir)
        self.token = process_token()
        self.stale_after, self.heartbeat = stale_after, heartbeat
        self.token_dirs = token_dirs  # folders whose files carry their writer's token in the name (spills)
        self.owners_dir, self.claims_dir = self.dir / "owners", self.dir / "claims"
        self.file = self.owners_dir / f"{self.token}.json"
        self.held: set[Path] = set()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._beat, name="usl-build-heartbeat", daemon=True)

    @property
    def scratch_dir(self) -> Path:
        """A folder for this process's own working files (removed on exit, or reaped after a kill)."""
        return self.dir / f"scratch-{self.token}"

    def info(self) -> dict[str, Any]:
        return {
            "token": self.token,
            "host": host_identity(),
            "hostname": socket.gethostname(),
            "pid": os.getpid(),
            "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        }

    def __enter__(self) -> Owner:
        _create_exclusive(self.file, self.info())  # a full or read-only disk: the caller's storage_faults
        self._thread.start()
        self.reap_stale_owners()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._stop.set()
        self._thread.join()
        for path in list(self.held):
            self._release(path)
        self._remove_leftovers(self.token)
        self.file.unlink(missing_ok=True)

    def _beat(self) -> None:
        while not self._stop.wait(self.heartbeat):
            with self._lock:
                paths = [self.file, *self.held]
            for path in paths:
                try:
                    os.utime(path)
                except OSError:  # released meanwhile, or a network disk's hiccup: beat again later
                    pass

    def others_alive(self) -> bool:
        """Whether another live process works in this folder now."""
        for path in self.owners_dir.glob("*.json"):
            found = _read(path)
            if path != self.file and found is not None and not is_stale(*found, self.stale_after):
                return True
        return False

    # ------------------------------------------------------------------ claims
    def _claim_path(self, name: str) -> Path:
        return self.claims_dir / f"{name}.json"

    def claim(self, name: str, on_takeover: Callable[[str], None] | None = None) -> bool:
        """Claim ``name``, taking it over if its holder is gone; False while a live process holds it.

        Whoever removes a gone holder's claim calls ``on_takeover(its token)`` at once (to delete
        that holder's partial files), even if another process then wins the new claim.
        """
        path = self._claim_path(name)
        for _ in range(3):
            try:
                _create_exclusive(path, self.info())
            except FileExistsError:
                found = _read(path)
                if found is not None:
                    if not is_stale(*found, self.stale_after):
                        return False
                    token = _holder(found[0]).get("token")
                    if self._remove_unchanged(path, found[0]) and token and on_takeover is not None:
                        on_takeover(token)
                continue
            with self._lock:
                self.held.add(path)
            return True
        return False

    def _remove_unchanged(self, path: Path, raw: bytes) -> bool:
        """Remove ``path`` if it still holds ``raw``: rename it aside first, so a fresh claim that
        replaced it meanwhile is put back, never deleted."""
        aside = path.with_name(f"{path.name}.reap-{self.token}")
        try:
            os.replace(path, aside)
        except FileNotFoundError:
            return False
        if aside.read_bytes() == raw:
            aside.unlink()
            return True
        try:
            os.link(aside, path)  # no-clobber restore
        except FileExistsError:
            pass
        aside.unlink()
        return False

    def holder(self, name: str) -> dict[str, Any]:
        """Who holds the claim ``name`` (the holder's ``info``; empty if nobody, or being written)."""
        found = _read(self._claim_path(name))
        return _holder(found[0]) if found is not None else {}

    def release(self, name: str) -> None:
        self._release(self._claim_path(name))

    def _release(self, path: Path) -> None:
        with self._lock:
            self.held.discard(path)
        found = _read(path)
        if found is not None and _holder(found[0]).get("token") == self.token:
            path.unlink(missing_ok=True)

    # ------------------------------------------------------------------ reaping
    def reap_stale_owners(self) -> list[str]:
        """Remove what owners that are gone left behind: temp files, spills, scratch, owner file."""
        reaped = []
        for path in sorted(self.owners_dir.glob("*.json")):
            found = _read(path)
            if path == self.file or found is None or not is_stale(*found, self.stale_after):
                continue
            self._remove_leftovers(path.stem)
            path.unlink(missing_ok=True)
            reaped.append(path.stem)
        return reaped

    def _remove_leftovers(self, token: str) -> None:
        """Temp files, spills and scratch of the process ``token`` (only it ever writes them)."""
        for directory in (self.dir, self.dir.parent):
            for tmp in temp_files_of(directory, token):
                tmp.unlink(missing_ok=True)
        for directory in self.token_dirs:
            for leftover in Path(directory).glob(f"*{token}*"):
                leftover.unlink(missing_ok=True)
        shutil.rmtree(self.dir / f"scratch-{token}", ignore_errors=True)


LOCK_DIR = ".lock"  # a folder's owner registry when one process at a time may write the folder


@contextmanager
def sole_writer(
    folder: Path, what: str, token_dirs: tuple[Path, ...] = (), stale_after: float = STALE_AFTER_SECONDS
) -> Iterator[Owner]:
    """Hold ``folder`` for this process while the block runs (``what``: the command, for the error).

    Another live process holding it makes this a UslError naming its host and pid; a holder that
    is gone (same rules as shard claims) is taken over, and its temp files in ``folder`` and in
    ``token_dirs`` (sub-folders with temp files, e.g. checkpoints) are reaped.
    """
    lock_dir = Path(folder) / LOCK_DIR
    try:
        with Owner(lock_dir, stale_after, token_dirs=token_dirs) as owner:
            if not owner.claim("folder"):
                holder = owner.holder("folder")
                who = (
                    f"pid {holder.get('pid', '?')} on {holder.get('hostname', '?')} since {holder.get('started', '?')}"
                )
                raise UslError(
                    f"{folder}: {what} is already writing here ({who}); wait for it to end or use another folder"
                )
            yield owner
    finally:
        for directory in (lock_dir / "claims", lock_dir / "owners", lock_dir):
            with suppress(OSError):  # another process's files are still there
                directory.rmdir()
