"""Atomic file writes and atomic output *sets*: the one implementation every writer in the project uses.

Single files (:func:`write_atomic`): a temp file is written beside the target, flushed and fsync'ed, given
the permissions an ordinary ``open()`` would give (``0o666 & ~umask``, not :func:`tempfile.mkstemp`'s
0600) and renamed over the target with :func:`os.replace`.  A reader never sees a half-written file; on a
Python exception the temp file is removed.  A process killed outright (SIGKILL, power loss) cannot clean
up, so temp names carry the writer's process id (``.<name>.<pid>.<random>.tmp``) and
:func:`clean_stale_temporaries` -- called by every write into a folder, once per folder and process --
removes those whose process is gone.

Output sets (:class:`OutputSet`): a verb that writes several files builds them in a staging folder beside
OUT (``.<OUT>.partial-<pid>``) and moves them into place at the end.  When OUT did not exist the staging
folder is renamed to OUT (one atomic rename: OUT is absent or complete).  When OUT exists, the files of
OUT that the new set does not replace (the user's own files, older outputs) are hard-linked into the
staging folder and the two folders are swapped by one ``renameat2(RENAME_EXCHANGE)`` (Linux): OUT is
unchanged or complete, never partial.  Where that call is not available the files are moved in one by
one and the manifest (``<verb>-manifest.json``, listing every file) is written last, so a run interrupted
while moving leaves OUT without a current manifest.  Stale staging folders of dead processes are removed
at the next run.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import threading
from pathlib import Path

from ._libc import libc_function
from .errors import DataFileError

__all__ = ["write_atomic", "write_atomic_text", "sync_folder", "file_mode", "dir_mode", "check_output_folder", "check_output_apart", "clean_stale_temporaries", "make_temp", "spill_folder", "OutputSet"]

_LOCK = threading.Lock()


def _load_exchange():
    """``renameat2(..., RENAME_EXCHANGE)`` from the C library, or None (not Linux, old glibc)."""
    import ctypes

    return libc_function("renameat2", (ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint))


_RENAMEAT2 = _load_exchange()
_HAS_EXCHANGE = _RENAMEAT2 is not None


def _exchange(a: Path, b: Path) -> bool:
    """Atomically swap two existing paths; False when the file system refuses (nothing changed then)."""
    if _RENAMEAT2 is None:
        return False
    at_fdcwd, rename_exchange = -100, 2
    return _RENAMEAT2(at_fdcwd, os.fsencode(str(a)), at_fdcwd, os.fsencode(str(b)), rename_exchange) == 0
_MODE: int | None = None
_CLEANED: set[str] = set()


def _umask() -> int:
    """The process umask (read once)."""
    global _MODE
    if _MODE is None:
        mask = None
        try:  # Linux: read the umask without changing it (thread-safe)
            with open("/proc/self/status", encoding="ascii") as fh:
                for line in fh:
                    if line.startswith("Umask:"):
                        mask = int(line.split()[1], 8)
                        break
        except (OSError, ValueError):
            mask = None
        if mask is None:
            with _LOCK:
                mask = os.umask(0o022)
                os.umask(mask)
        _MODE = mask
    return _MODE


def file_mode() -> int:
    """Permission bits an ordinary ``open(path, "w")`` would give a new file: ``0o666 & ~umask``."""
    return 0o666 & ~_umask()


def dir_mode() -> int:
    """Permission bits ``os.mkdir`` would give a new folder: ``0o777 & ~umask``."""
    return 0o777 & ~_umask()


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # exists but not ours (EPERM)
        return True
    return True


def _owner_pid(name: str, marker: str) -> int | None:
    """The pid embedded in a temp name (``....<marker><pid>...``), or None."""
    i = name.rfind(marker)
    if i < 0:
        return None
    digits = ""
    for ch in name[i + len(marker):]:
        if not ch.isdigit():
            break
        digits += ch
    return int(digits) if digits else None


#: endings of the temp files :func:`make_temp` names (``.tmp``; the GeoTIFF writer's ``.tmp.tif`` / ``.cog.tif``)
_TEMP_SUFFIXES = (".tmp", ".tmp.tif", ".cog.tif")


def spill_folder(parent: str | os.PathLike, what: str) -> Path:
    """A new scratch folder ``<parent>/.<what>.spill-<pid>-<random>`` that no other run shares (created here).

    A run killed outright leaves it behind; :func:`clean_stale_temporaries` removes it once its process is gone.
    """
    parent = Path(parent)
    parent.mkdir(parents=True, exist_ok=True)
    return Path(tempfile.mkdtemp(prefix=f".{what}.spill-{os.getpid()}-", dir=parent))


def clean_stale_temporaries(folder: str | os.PathLike, *, force: bool = False) -> list[Path]:
    """Remove temp files (``.*.<pid>.*.tmp``, ``.tmp.tif``, ``.cog.tif``), staging folders (``.*.partial-<pid>-*``)
    and spill folders (``.*.spill-<pid>-*``) in ``folder`` left by processes that no longer run.  Returns what was removed.  Done once per folder and process
    unless ``force``."""
    d = Path(folder)
    key = str(d.resolve()) if d.exists() else str(d)
    with _LOCK:
        if key in _CLEANED and not force:
            return []
        _CLEANED.add(key)
    removed: list[Path] = []
    try:
        entries = list(os.scandir(d))
    except OSError:
        return removed
    for e in entries:
        n = e.name
        if not n.startswith("."):
            continue
        try:
            suffix = next((s for s in _TEMP_SUFFIXES if n.endswith(s)), None)
            if suffix is not None and e.is_file(follow_symlinks=False):
                parts = n[:-len(suffix)].split(".")
                pid = int(parts[-2]) if len(parts) >= 3 and parts[-2].isdigit() else None
                if pid is not None and not _pid_alive(pid):
                    os.unlink(e.path)
                    removed.append(Path(e.path))
            elif e.is_dir(follow_symlinks=False) and (".partial-" in n or ".spill-" in n):
                pid = _owner_pid(n, ".partial-" if ".partial-" in n else ".spill-")
                if pid is not None and not _pid_alive(pid):
                    shutil.rmtree(e.path, ignore_errors=True)
                    removed.append(Path(e.path))
        except OSError:
            continue
    return removed


def make_temp(path: str | os.PathLike, suffix: str = ".tmp") -> tuple[int, Path]:
    """Open a temp file beside ``path`` for an atomic write: ``(fd, temp_path)``.

    The name carries this process's id (so a killed run's leftovers are recognised and removed), the mode
    is :func:`file_mode`.  The caller writes, then ``os.replace(temp_path, path)``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    clean_stale_temporaries(path.parent)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{os.getpid()}.", suffix=suffix, dir=path.parent)
    try:
        os.fchmod(fd, file_mode())
    except (OSError, AttributeError):  # pragma: no cover - platforms without fchmod
        pass
    return fd, Path(tmp)


def write_atomic(path: str | os.PathLike, data: bytes, *, durable: bool = True) -> Path:
    """Write ``data`` to ``path`` atomically, creating missing parent folders.

    ``durable=False`` leaves out the fsync before the rename: for files written into a staging folder that
    :func:`sync_folder` flushes once before it is published (one journal commit instead of one per file;
    the survey writes several hundred feature and match files). A reader still never sees a half-written file.

    Raises
    ------
    DataFileError
        When the folder cannot be created or the file cannot be written; names the path.
    """
    path = Path(path)
    try:
        fd, tmp = make_temp(path)
    except OSError as exc:
        raise DataFileError(f"{path}: cannot write ({exc.strerror or exc})") from exc
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            if durable:
                os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        if isinstance(exc, OSError) and not isinstance(exc, DataFileError):
            raise DataFileError(f"{path}: cannot write ({exc.strerror or exc})") from exc
        raise
    return path


def sync_folder(folder: str | os.PathLike) -> None:
    """Flush every file under ``folder`` to disk before the folder is published (renamed into place).

    One ``syncfs`` of the folder's file system (Linux), else an fsync of every file; then the folders themselves.
    Errors are reported as :class:`DataFileError` naming the folder.
    """
    folder = Path(folder)
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError as exc:
        raise DataFileError(f"{folder}: cannot open the folder to flush it ({exc.strerror or exc})") from exc
    try:
        if _syncfs(fd):
            return
        for root, dirs, files in os.walk(folder):
            for name in files + dirs:
                p = os.path.join(root, name)
                try:
                    f2 = os.open(p, os.O_RDONLY)
                except OSError:
                    continue  # removed meanwhile (a temp file)
                try:
                    os.fsync(f2)
                finally:
                    os.close(f2)
        os.fsync(fd)
    except OSError as exc:
        raise DataFileError(f"{folder}: cannot flush the folder to disk ({exc.strerror or exc})") from exc
    finally:
        os.close(fd)


def _syncfs(fd: int) -> bool:
    """``syncfs(fd)`` from the C library (Linux); False where it is not available or fails."""
    import ctypes

    fn = libc_function("syncfs", (ctypes.c_int,))
    return fn is not None and fn(fd) == 0


def write_atomic_text(path: str | os.PathLike, text: str) -> Path:
    """UTF-8 text with ``\\n`` line ends, written by :func:`write_atomic`."""
    return write_atomic(path, text.encode("utf-8"))


def check_output_folder(out: str | os.PathLike, what: str = "output folder") -> Path:
    """Refuse an OUT that cannot become a folder we can write into, before any work is done.

    Raises
    ------
    DataFileError
        OUT is an existing file, or its folder (or OUT itself) is not writable.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise DataFileError(f"{what} {out}: is an existing file, expected a folder (or a name to create)")
    probe = out if out.is_dir() else out.parent
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if probe.exists() and not probe.is_dir():
        raise DataFileError(f"{what} {out}: {probe} is a file, not a folder")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise DataFileError(f"{what} {out}: {probe} is not writable (permission denied)")
    return out


def check_output_apart(out: str | os.PathLike, inputs, what: str = "-o") -> None:
    """Refuse an OUT that is an input folder, lies inside one or contains one, before anything is read.

    Parameters
    ----------
    out : the output folder the user named (a symlink is followed: its target is what is compared)
    inputs : iterable of ``(label, path)``: the input folders, ``label`` naming them in the message (``"survey
        folder"``); an input file refuses only an OUT that is its own folder (``survey flight.mp4 -o out`` beside the
        video is usual)
    what : how the message names OUT

    Raises
    ------
    DataFileError
        OUT and an input folder are one, or one holds the other: the outputs would mix with the user's input files
        (and a rerun would read its own outputs as inputs).
    """
    o = Path(out).resolve()
    via = f" (a link to {o})" if Path(out).is_symlink() else ""
    for label, p in inputs:
        p = Path(p)
        folder = p if p.is_dir() else p.parent
        f = folder.resolve()
        if o == f:
            how = "is"
        elif p.is_dir() and o.is_relative_to(f):
            how = "lies inside"
        elif p.is_dir() and f.is_relative_to(o):
            how = "contains"
        else:
            continue
        raise DataFileError(f"{what} {out}{via}: {how} the {label} {folder}; expected an output folder apart from the "
                            "inputs (neither one of their folders, nor inside or around one)")


class OutputSet:
    """Write a set of files so that OUT is either unchanged or complete (see the module docstring).

    Use as a context manager; ``path(name)`` gives where to write ``name`` (inside the staging folder),
    ``commit(manifest)`` moves everything into OUT.  Leaving the ``with`` block without ``commit``
    (an exception, or nothing to write) removes the staging folder and leaves OUT untouched.

    Parameters
    ----------
    out : path
        The output folder the user named.
    verb : str
        Names the manifest (``<verb>-manifest.json``).
    obsolete : names in OUT that the verb's older versions left there (scratch folders without an owner):
        not carried into the new set, removed when it is published.
    """

    def __init__(self, out: str | os.PathLike, verb: str, *, obsolete: tuple[str, ...] = ()):
        self.out = check_output_folder(out)
        self.verb = verb
        self.obsolete = tuple(obsolete)
        parent = self.out.parent
        try:
            parent.mkdir(parents=True, exist_ok=True)
            clean_stale_temporaries(parent)
            if self.out.is_dir():
                clean_stale_temporaries(self.out)
            self.stage = Path(tempfile.mkdtemp(prefix=f".{self.out.name}.partial-{os.getpid()}-", dir=parent))
            os.chmod(self.stage, dir_mode())
        except OSError as exc:
            raise DataFileError(f"output folder {self.out}: cannot be created ({exc.strerror or exc})") from None
        self.committed = False

    @property
    def manifest_name(self) -> str:
        return f"{self.verb}-manifest.json"

    def path(self, name: str) -> Path:
        """Where to write the output ``name`` (relative, ``/``-separated) during the run."""
        p = self.stage / name
        p.parent.mkdir(parents=True, exist_ok=True)
        return p

    def final_path(self, name: str) -> Path:
        return self.out / name

    def files(self) -> list[str]:
        return sorted(p.relative_to(self.stage).as_posix() for p in self.stage.rglob("*")
                      if p.is_file() and not p.name.startswith("."))

    def commit(self, manifest: dict | None = None) -> list[Path]:
        """Move the staged files into OUT; the manifest (``files`` + ``manifest``) is written last."""
        names = self.files()
        doc = {"verb": self.verb, "complete": True, "files": names, **(manifest or {})}
        try:
            if not self.out.exists() and self._publish_new(doc):
                pass
            elif self._swap_into_existing(doc):
                pass
            else:
                stale = self.out / self.manifest_name
                if stale.exists():  # the set is being replaced: no manifest until it is complete
                    os.unlink(stale)
                for n in self.obsolete:
                    old = self.out / n
                    if old.is_dir() and not old.is_symlink():
                        shutil.rmtree(old, ignore_errors=True)
                for n in names:
                    dst = self.out / n
                    dst.parent.mkdir(parents=True, exist_ok=True)
                    os.replace(self.stage / n, dst)
                write_atomic_text(self.out / self.manifest_name, json.dumps(doc, indent=1) + "\n")
                shutil.rmtree(self.stage, ignore_errors=True)
        except OSError as exc:
            raise DataFileError(f"output folder {self.out}: cannot move the outputs into place ({exc.strerror or exc})") from None
        self.committed = True
        return [self.out / n for n in names]

    def _publish_new(self, doc: dict) -> bool:
        """Rename the stage to the absent OUT. False when another run published OUT meanwhile (two runs into one OUT
        at once): the caller then publishes over it as over any existing OUT."""
        import errno

        write_atomic_text(self.stage / self.manifest_name, json.dumps(doc, indent=1) + "\n")
        try:
            os.replace(self.stage, self.out)
            return True
        except OSError as exc:
            if exc.errno not in (errno.ENOTEMPTY, errno.EEXIST, errno.EISDIR) or not self.out.is_dir():
                raise
        os.unlink(self.stage / self.manifest_name)
        return False

    def _swap_into_existing(self, doc: dict) -> bool:
        """Carry OUT's other files into the stage (hard links) and swap the folders atomically.

        Returns False, with nothing in OUT changed, where the atomic exchange is unavailable.
        """
        if not _HAS_EXCHANGE or not self.out.is_dir() or self.out.is_symlink():
            return False
        if os.stat(self.out).st_dev != os.stat(self.stage).st_dev:  # OUT is a mount point: no exchange
            return False
        new = set(self.files())
        for root, dirs, files in os.walk(self.out):
            rel_root = Path(root).relative_to(self.out)
            if rel_root == Path("."):
                dirs[:] = [d for d in dirs if d not in self.obsolete]
            for d in dirs:
                if os.path.islink(os.path.join(root, d)):  # a symlinked folder is carried as a link, not walked
                    files.append(d)
            dirs[:] = [d for d in dirs if not os.path.islink(os.path.join(root, d))]
            for f in files:
                rel = (rel_root / f).as_posix()
                if rel in new or rel == self.manifest_name:
                    continue
                src, dst = Path(root) / f, self.stage / rel
                dst.parent.mkdir(parents=True, exist_ok=True)
                if src.is_symlink():
                    os.symlink(os.readlink(src), dst)
                else:
                    try:
                        os.link(src, dst)
                    except OSError:
                        shutil.copy2(src, dst)
        write_atomic_text(self.stage / self.manifest_name, json.dumps(doc, indent=1) + "\n")
        if not _exchange(self.stage, self.out):
            return False
        shutil.rmtree(self.stage, ignore_errors=True)  # now the previous OUT (its user files are linked in OUT)
        return True

    def abort(self) -> None:
        shutil.rmtree(self.stage, ignore_errors=True)

    def __enter__(self) -> "OutputSet":
        return self

    def __exit__(self, *exc) -> None:
        if not self.committed:
            self.abort()
