"""Where results go: checked before the work starts, held by one run, written whole or not at all.

Every verb that writes claims its outputs first (`claim_file`, `claim_directory`), so a bad
path costs a one-line error and no work; files are written under a temporary name beside the
target and renamed over it at the end (`atomic_paths`), so an interruption leaves the old
file or none, never half a new one.

A claim is held for the whole run, not only checked at its start: two runs to one name would
both find it free, and the later would silently replace the earlier's result (with
--overwrite too: overwriting replaces a finished file, not a run still writing it). It is an
exclusive `flock` of a claim file beside the output (.NAME.claim; inside a claimed
directory, .claim), taken without waiting, so the second run is refused in one line (a cache
that one run makes for all waits instead). The kernel lets the lock go when its process ends
however it ends, so a run killed with -9 leaves a claim file that nobody locks: the next run
takes it, and removes that run's temporaries (`remove_stale_temporaries`). A claim ends when
the call that took it returns (`claim_scope`), or with the process.
"""
from __future__ import annotations

import errno
import fcntl
import glob
import hashlib
import os
import re
import shutil
import stat
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path

from .errors import XvoeError

__all__ = ["claim_file", "refuse_overlap", "claim_directory", "check_name_length", "hold", "release",
           "claim_scope", "parts_folder", "temporary_name", "remove_stale_temporaries", "atomic_paths",
           "no_space", "refusal", "nearly_full", "writing", "replace_together"]

# the outputs this process holds, by absolute path: the descriptor that holds each one's lock
_held: dict[Path, int] = {}
# the directories this process made for its outputs, in the order made (`claim_scope` removes a failed call's)
_made: list[Path] = []


def claim_file(path: str | os.PathLike, overwrite: bool = False, *, what: str = "--out",
               wait: bool = False) -> Path:
    """`path` as a file that can be written now: a name, not a directory, absent unless
    `overwrite`, in a directory that exists (made here) and can be written, and held by this
    process (`hold`) until the call that claimed it returns (`claim_scope`). `wait`: wait for a
    run that holds it, rather than refuse (a shared cache that one run makes for all)."""
    if str(path).strip() == "":
        raise XvoeError(f"{what} is empty; give a file name")
    if str(path).endswith(("/", os.sep)):
        raise XvoeError(f"{path} ends in a slash, as a directory does; {what} needs a file name")
    check_name_length(path, what)
    path = Path(path)
    if path.is_dir():
        raise XvoeError(f"{path} is a directory; {what} needs a file name")
    if path.exists() and not overwrite:
        raise XvoeError(f"{path} exists; pass --overwrite to replace it")
    _writable_directory(path.parent)
    taken = hold(path, wait=wait)
    try:
        if path.exists() and not overwrite:     # written by a run that ended since the look above
            raise XvoeError(f"{path} exists; pass --overwrite to replace it")
        if os.path.lexists(path):
            _replaceable(path)
    except XvoeError:
        if taken:
            release(path)
        raise
    remove_stale_temporaries(path)
    return path


def _replaceable(path: Path) -> None:
    """Refuse before the work a file whose replacement the folder will refuse at the end: in a
    sticky folder (as /tmp) only the file's owner, the folder's or root may replace it."""
    folder = path.parent.stat()
    if folder.st_mode & stat.S_ISVTX and os.geteuid() not in (0, folder.st_uid, path.lstat().st_uid):
        raise XvoeError(f"cannot replace {path}: it is another user's, in a folder where only its owner may "
                        "replace it")


def refuse_overlap(inputs: list[str | os.PathLike], output: str | os.PathLike, suffixes: tuple[str, ...],
                   *, what: str = "--out") -> None:
    """Refuse, before any work, an output that is one of the command's inputs (the same file by
    any name: both resolved through symbolic links) or whose suffix is not what is written. A
    symbolic link at the output is replaced itself, never its target, so a link is refused only
    where it leads to an input."""
    out = Path(output)
    if str(output).strip() == "":
        return      # claim_file names an empty name
    check_name_length(out, what)
    if out.is_dir():
        return      # claim_file names a directory
    for source in inputs:
        if Path(source).resolve() == out.resolve():
            raise XvoeError(f"{what} {out} is the input {source}; write the result to another file")
    if out.suffix.lower() not in suffixes:
        named = " or ".join([", ".join(suffixes[:-1]), suffixes[-1]] if len(suffixes) > 1 else suffixes)
        raise XvoeError(f"{what} must end in {named}, not {out.suffix or 'nothing'}")


def claim_directory(path: str | os.PathLike, *, what: str = "--out", make: bool = True,
                    whole: bool = False) -> Path:
    """`path` as a directory to write into: not a file, writable, and made if missing (unless
    `make` is false: a check before the work, which writes nothing). `whole`: held by this
    process as one output (`hold`), as a report is; a run directory, whose stages may train in
    other processes, is held stage by stage instead (each stage's checkpoint)."""
    if str(path).strip() == "":
        raise XvoeError(f"{what} is empty; give a directory")
    check_name_length(path, what)
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise XvoeError(f"{path} is a file; {what} needs a directory")
    _writable_directory(path, make)
    if whole and make:
        hold(path)
    return path


def check_name_length(path: str | os.PathLike, what: str = "--out") -> None:
    """Refuse, before the work (and before any look at the path, which such a name makes fail),
    a name longer than its file system takes: 255 bytes on most."""
    path = Path(path)
    existing = next((folder for folder in [path, *path.parents] if os.path.isdir(folder)), Path("."))
    try:
        limit = os.pathconf(existing, "PC_NAME_MAX")
    except (OSError, ValueError):
        limit = 255
    for part in path.parts:
        if (length := len(os.fsencode(part))) > limit:
            raise XvoeError(f"{what} holds a name of {length} bytes ({part[:16]}...), past the {limit} its file "
                            "system takes; give a shorter name")


def _hidden_name(path: Path, kind: str) -> Path:
    """`path`'s hidden companion of `kind` (claim, tmp-PID, old-PID, parts-PID): .NAME.KIND where
    that is short, so that a name the file system takes has companions it takes too; a long NAME
    is cut and a hash of it keeps companions of different names apart."""
    name = path.name
    if len(os.fsencode(name)) > _NAME_KEPT:
        name = os.fsencode(name)[:_NAME_KEPT - 9].decode(errors="ignore") + "~" + \
            hashlib.sha256(os.fsencode(path.name)).hexdigest()[:8]
    return path.with_name(f".{name}.{kind}")


_NAME_KEPT = 200        # bytes of an output's name kept in its companions' names (room for .tmp-PID)


def _claim_name(path: Path) -> Path:
    """The file whose lock holds `path`: beside a file, inside a directory."""
    return path / ".claim" if path.is_dir() else _hidden_name(path, "claim")


def hold(path: str | os.PathLike, *, wait: bool = False) -> bool:
    """Hold `path` for this process: refused in one line while another process holds it (or,
    with `wait`, taken once it lets go). True where taken now, False where held already."""
    key = Path(os.path.abspath(path))
    if key in _held:
        return False
    lock = _claim_name(key)
    while True:
        descriptor = _open_claim(lock, path)
        try:
            fcntl.flock(descriptor, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
        except BlockingIOError:
            holder = os.pread(descriptor, 20, 0).decode(errors="replace").strip()
            os.close(descriptor)
            raise XvoeError(f"{path} is being written by another run{f' (process {holder})' if holder else ''}; "
                            "wait for it to end or write elsewhere") from None
        except BaseException:
            os.close(descriptor)
            raise
        with suppress(FileNotFoundError):
            if os.path.samestat(os.fstat(descriptor), os.stat(lock)):
                break
        os.close(descriptor)        # its holder removed that file as it let go: lock the one there now
    with suppress(OSError):         # the holder's process, for the refusal of another run to name
        os.ftruncate(descriptor, 0)
        os.pwrite(descriptor, f"{os.getpid()}\n".encode(), 0)
    _held[key] = descriptor
    return True


def _open_claim(lock: Path, path: str | os.PathLike) -> int:
    try:
        return os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
    except PermissionError:
        with suppress(OSError):     # another user's claim file, in a folder only its owner may change: reading locks it
            return os.open(lock, os.O_RDONLY)
        raise XvoeError(f"cannot claim {path}: permission denied for {lock}") from None
    except OSError as error:
        raise XvoeError(f"cannot claim {path}: {refusal(error) or error.strerror or error} ({lock})") from None


def release(path: str | os.PathLike) -> None:
    """Let go of a path this process holds (nothing if it does not). The claim file goes first,
    while still locked, so a run waiting on it looks again and locks the next one."""
    key = Path(os.path.abspath(path))
    descriptor = _held.pop(key, None)
    if descriptor is None:
        return
    with suppress(OSError):
        _claim_name(key).unlink()
    fcntl.flock(descriptor, fcntl.LOCK_UN)      # a forked worker's copy of the descriptor must not keep it
    os.close(descriptor)


@contextmanager
def claim_scope() -> Iterator[None]:
    """The claims taken in the block (or, as a decorator, in the call) end with it, whether it
    wrote its outputs or failed: a notebook's failed call blocks no later run."""
    before, made = set(_held), len(_made)
    try:
        yield
    except BaseException:
        _release_since(before)
        _remove_made_since(made)
        raise
    _release_since(before)


def _release_since(before: set[Path]) -> None:
    for path in set(_held) - before:
        release(path)


def _remove_made_since(count: int) -> None:
    """Remove the directories made since `_made` held `count`, deepest first, where a failed call
    left them empty: an error found in the middle of the work leaves nothing behind."""
    while len(_made) > count:
        with suppress(OSError):      # not empty (something was written there) or gone: left as it is
            _made.pop().rmdir()


def _writable_directory(directory: Path, make: bool = True) -> None:
    existing = directory
    while not existing.exists():
        if existing.parent == existing:
            break
        existing = existing.parent
    if not existing.is_dir():
        raise XvoeError(f"cannot write under {directory}: {existing} is a file")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise XvoeError(f"cannot write to {existing}: {_unwritable(existing)}")
    if not make:
        return
    missing = [directory, *directory.parents][:len(directory.parents) + 1]
    missing = [folder for folder in missing if not folder.exists()]
    try:
        directory.mkdir(parents=True, exist_ok=True)
        _made.extend(reversed(missing))
    except OSError as error:
        raise XvoeError(f"cannot make the directory {directory}: {refusal(error) or error.strerror}") from None


def _unwritable(folder: Path) -> str:
    """Why `folder`, which this process may not write to, refuses: its file system is mounted
    read-only (no change of permissions helps), or the permissions say no."""
    with suppress(OSError):
        if os.statvfs(folder).f_flag & os.ST_RDONLY:
            return "read-only file system"
    return "permission denied"


def parts_folder(path: Path) -> Path:
    """The folder beside `path` where this process writes the parts it joins into `path`."""
    return _hidden_name(path, f"parts-{os.getpid()}")


def temporary_name(path: Path) -> Path:
    """The name a file is written under before it takes `path`'s place (this process's)."""
    return _hidden_name(path, f"tmp-{os.getpid()}")


def _aside_name(path: Path) -> Path:
    """The name the old file at `path` is moved to while the new one takes its place."""
    return _hidden_name(path, f"old-{os.getpid()}")


def remove_stale_temporaries(path: Path) -> None:
    """Delete the temporary files and folders of `path` left by processes that are gone (killed
    with -9); an old file such a process had moved aside goes back where nothing took its place."""
    stem = _hidden_name(path, "").name
    pattern = re.compile(rf"^{re.escape(stem)}(tmp|old|parts)-(\d+)$")
    for candidate in path.parent.glob(f"{glob.escape(stem)}*-*"):
        match = pattern.match(candidate.name)
        if not match or _alive(int(match.group(2))):
            continue
        if match.group(1) == "old" and not os.path.lexists(path):
            os.replace(candidate, path)
        elif candidate.is_dir() and not candidate.is_symlink():
            shutil.rmtree(candidate, ignore_errors=True)
        else:
            candidate.unlink(missing_ok=True)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


@contextmanager
def atomic_paths(*paths: Path) -> Iterator[list[Path]]:
    """Temporary names for `paths`, held (`hold`) and renamed over them together when the block
    succeeds (`replace_together`), removed when it fails. Put the file that readers look for
    first last: it is the commit."""
    with claim_scope():
        for path in paths:
            hold(path)
            remove_stale_temporaries(path)
        temporaries = [temporary_name(path) for path in paths]
        try:
            with writing(paths[-1]):
                yield temporaries
                replace_together(temporaries, list(paths))
        finally:
            for temporary in temporaries:
                if temporary.is_dir() and not temporary.is_symlink():
                    shutil.rmtree(temporary, ignore_errors=True)
                else:       # a folder that stopped taking changes keeps it: the next run removes it
                    with suppress(OSError):
                        temporary.unlink(missing_ok=True)


# what a write meets on a full disk (or past a quota, or past the size limit of a process's files)
_NO_SPACE = {errno.ENOSPC: "no space left on device", errno.EDQUOT: "disk quota exceeded",
             errno.EFBIG: "file too large for this process or file system"}
# what a write meets where the folder stopped taking files after the run's checks (its
# permissions changed, its file system remounted read-only)
_REFUSED = _NO_SPACE | {errno.EACCES: "permission denied", errno.EPERM: "operation not permitted",
                        errno.EROFS: "read-only file system"}


def no_space(error: BaseException) -> str | None:
    """What is full, where `error` is a write that found no room, else None."""
    return _errno_text(error, _NO_SPACE)


def refusal(error: BaseException) -> str | None:
    """Why the file system refused a write, where `error` is such a refusal (no room, no
    permission, read-only), else None."""
    return _errno_text(error, _REFUSED)


def _errno_text(error: BaseException, texts: dict[int, str]) -> str | None:
    """HDF5 names the errno only in its message, and a failed flush as it closes a file is a
    RuntimeError."""
    if isinstance(error, OSError) and error.errno in texts:
        return texts[error.errno]
    if isinstance(error, (OSError, RuntimeError)):
        return next((what for number, what in texts.items() if f"errno = {number}," in str(error)), None)
    return None


def nearly_full(folder: Path) -> bool:
    """Whether `folder`'s file system has under a megabyte left: what a writer in another
    process (the video encoder) that stopped without saying why most likely met."""
    try:
        usage = os.statvfs(folder)
    except OSError:
        return False
    return usage.f_bavail * usage.f_frsize < 2**20


@contextmanager
def writing(path: str | os.PathLike) -> Iterator[None]:
    """A full disk, or a folder that stopped taking files, met in the block is named in one
    line, by the output it was writing: its final name, not a temporary's, and where blocks nest
    (a report's figures), the outermost's."""
    _writing.append(Path(path))
    try:
        yield
    except (OSError, RuntimeError) as error:
        if (what := refusal(error)) is None:
            raise
        raise XvoeError(f"{what} writing {_writing[0]}") from None
    finally:
        _writing.pop()


_writing: list[Path] = []      # the outputs whose `writing` blocks this process is in, outermost first


def replace_together(temporaries: list[Path], paths: list[Path]) -> None:
    """Rename each temporary over its path, in order, all or none. The old files are moved
    aside first, which a directory refuses exactly where it refuses replacing them (a file of
    another user in a sticky directory), so a refusal puts every old file back, removes every
    new one and costs a one-line error: a result of several files stays a consistent set."""
    aside: list[tuple[Path, Path]] = []
    placed: list[Path] = []
    current = paths[0] if paths else None
    try:
        for current in paths:
            if os.path.lexists(current):
                os.replace(current, _aside_name(current))
                aside.append((current, _aside_name(current)))
        for temporary, current in zip(temporaries, paths):
            os.replace(temporary, current)
            placed.append(current)
    except BaseException as error:
        for path in placed:
            path.unlink(missing_ok=True)
        for path, old in aside:
            os.replace(old, path)
        if isinstance(error, OSError):
            raise XvoeError(f"cannot replace {current}: {refusal(error) or error.strerror or error}; "
                            "the files there were left as they were") from None
        raise
    for _, old in aside:
        old.unlink()
