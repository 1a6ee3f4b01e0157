"""Output paths of the commands: checked before the work starts, replaced whole.

A command checks every path it will write before it starts a long computation, so that a
mistyped ``--out`` costs a second, not a gain build: ``check_file`` and ``check_dir`` refuse a
path that cannot be written with ``OutputPathError`` (the flag, the path and why, in one
line). The check creates a file in the target directory to see that it can, because neither
permission bits (ignored for root) nor ``os.access`` (blind to file systems that refuse
writes) say so; it removes that file and any directory it created for it again.

``replacing`` writes under a temporary name in the target's directory and moves the file into
place only when it is complete, so an interrupted command leaves either the previous file or
the new one, never half of one.
"""

from __future__ import annotations

import errno
import os
import secrets
import shutil
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


class OutputPathError(Exception):
    """An output path cannot be written."""

    def __init__(self, what: str, path: str | Path, why: str) -> None:
        self.what = what
        self.path = str(path)
        self.why = why
        super().__init__(f"{what} {path}: cannot write there ({why})")


def _reason(exc: OSError) -> str:
    if exc.errno in (errno.EACCES, errno.EPERM):
        return "permission denied"
    return (exc.strerror or str(exc)).lower()


def _temporary(target: Path) -> Path:
    """Create an empty file next to ``target`` (mode from the umask), keeping its suffix so
    that writers that choose a format by suffix (matplotlib, numpy's ``.gz``) still do."""
    temp = target.with_name(f".{target.stem}.{secrets.token_hex(4)}.partial{target.suffix}")
    os.close(os.open(temp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666))
    return temp


def _check_writable_dir(directory: Path, what: str, shown: Path) -> None:
    """``directory`` exists or can be created, and a file can be created in it."""
    created: list[Path] = []
    try:
        missing = []
        existing = directory
        while not existing.exists():
            missing.append(existing)
            existing = existing.parent
        if not existing.is_dir():
            raise OutputPathError(what, shown, f"{existing} is not a directory")
        for d in reversed(missing):
            d.mkdir()
            created.append(d)
        _temporary(directory / "beamctl-check").unlink()
    except OSError as exc:
        raise OutputPathError(what, shown, _reason(exc)) from None
    finally:
        for d in reversed(created):
            try:
                d.rmdir()
            except OSError:        # someone else wrote into it meanwhile: theirs now
                break


def check_file(path: str | Path, what: str) -> Path:
    """``path`` can be written as a file (``what`` names it: the flag or config key)."""
    p = Path(path)
    try:
        if p.is_dir():
            raise OutputPathError(what, p, "it is a directory")
        if p.exists():
            if not os.access(p, os.W_OK):
                raise OutputPathError(what, p, "permission denied")
            if not p.is_file():      # a device or FIFO (/dev/null, /dev/stdout): written in place
                return p
    except OSError as exc:
        raise OutputPathError(what, p, _reason(exc)) from None
    _check_writable_dir(p.parent, what, p)
    return p


def check_new_file(path: str | Path, what: str) -> Path:
    """``path`` can be written as a file and holds nothing yet: for a recording, which is never
    overwritten (a name with ``strftime`` fields such as ``%Y%m%d-%H%M%S`` gives each run its
    own file; they are filled in here)."""
    p = Path(time.strftime(str(path)))
    if p.exists() and p.is_file():
        raise OutputPathError(what, p, "a recording is there already and is never overwritten; "
                                       "give a new name, or one with the time in it such as "
                                       "telemetry-%Y%m%d-%H%M%S.btl")
    return check_file(p, what)


def check_dir(path: str | Path, what: str) -> Path:
    """``path`` is, or can be made, a directory to write files into."""
    p = Path(path)
    try:
        if p.exists() and not p.is_dir():
            raise OutputPathError(what, p, "it is a file, not a directory")
    except OSError as exc:
        raise OutputPathError(what, p, _reason(exc)) from None
    _check_writable_dir(p, what, p)
    return p


@contextmanager
def replacing(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path next to ``path`` to write to; when the block completes, move it
    onto ``path`` (with the mode of the file it replaces); if the block fails or is
    interrupted, remove it. A device or FIFO is written in place."""
    target = Path(path)
    if target.exists() and not target.is_file():
        yield target
        return
    target.parent.mkdir(parents=True, exist_ok=True)
    temp = _temporary(target)
    try:
        yield temp
        if target.exists():
            shutil.copymode(target, temp)
        fd = os.open(temp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(temp, target)
    except BaseException:
        temp.unlink(missing_ok=True)
        raise


def write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` whole (through ``replacing``)."""
    with replacing(path) as temp:
        temp.write_text(text)
    return Path(path)
