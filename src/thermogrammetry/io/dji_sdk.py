"""Loading DJI's Thermal SDK library (``libdirp``) given by path: checks, then the plugins, then the library.

DJI's Linux SDK (v1.7) ``libdirp.so`` opens its model plugins (``libv_dirp.so``, ``libv_iirp.so``, ...) with
``dlopen`` by bare name, which the dynamic loader finds only on ``LD_LIBRARY_PATH``: without it every file fails
with ``dirp_create_from_rjpeg returned -16``. :func:`load_dji_sdk` first loads the SDK folder's ``libexif*``,
``libMicro*`` and ``libv_*`` shared libraries with ``RTLD_GLOBAL`` (a library already loaded is found by its
soname), retrying those that failed (a plugin that needs another one) until no further one loads, then
``libdirp`` itself; no environment variable is needed.

Before anything is loaded the path is checked: a file, an ELF shared library (on Linux), of this machine's
architecture and word size (the ELF header's ``EI_CLASS`` and ``e_machine``), exporting
``dirp_create_from_rjpeg``. Each refusal is a :class:`~thermogrammetry.errors.ConfigError` naming the path,
what is wrong and what to install.
"""

from __future__ import annotations

import ctypes
import os
import platform
import struct
import sys
import threading
from pathlib import Path

from ..errors import ConfigError

__all__ = ["SDK_ENV", "INSTALL_HINT", "check_dji_sdk", "load_dji_sdk", "sdk_path", "elf_machine", "machine_code"]

SDK_ENV = "THERMOGRAMMETRY_DJI_TSDK"

INSTALL_HINT = (
    "install DJI Thermal SDK (the 'DJI TSDK', a free download from DJI) and point --dji-sdk (or "
    f"${SDK_ENV}) at its libdirp.so for this machine (the SDK's linux/release_x64 folder; libdirp.dll on "
    "Windows), left in its folder beside its libv_*.so plugins"
)

#: ELF e_machine of the architectures Python runs on (platform.machine() -> code, name)
_MACHINES = {
    "x86_64": (62, "x86-64"), "amd64": (62, "x86-64"), "i386": (3, "x86"), "i486": (3, "x86"), "i586": (3, "x86"),
    "i686": (3, "x86"), "x86": (3, "x86"), "aarch64": (183, "AArch64"), "arm64": (183, "AArch64"),
    "armv7l": (40, "ARM"), "armv6l": (40, "ARM"), "arm": (40, "ARM"), "ppc64le": (21, "PowerPC64"),
    "ppc64": (21, "PowerPC64"), "s390x": (22, "S/390"), "riscv64": (243, "RISC-V"), "loongarch64": (258, "LoongArch"),
}
_NAMES = {code: name for code, name in _MACHINES.values()} | {8: "MIPS", 2: "SPARC", 43: "SPARC V9", 50: "IA-64"}

#: file name prefixes of the SDK folder's libraries loaded before libdirp (its plugins and their dependencies)
PRELOAD_PREFIXES = ("libexif", "libMicro", "libv_")

_LOCK = threading.Lock()
_LOADED: dict[str, ctypes.CDLL] = {}


def machine_code() -> tuple[int | None, str]:
    """(ELF e_machine, name) of the running interpreter's architecture; (None, name) when unknown."""
    m = platform.machine().lower()
    code, name = _MACHINES.get(m, (None, m or "unknown"))
    return code, name


def elf_machine(path: str | os.PathLike) -> tuple[int, int] | None:
    """(EI_CLASS, e_machine) of an ELF file: class 1 = 32-bit, 2 = 64-bit; None when ``path`` is not ELF."""
    with open(path, "rb") as fh:
        head = fh.read(20)
    if len(head) < 20 or head[:4] != b"\x7fELF":
        return None
    order = "<" if head[5] != 2 else ">"
    return head[4], struct.unpack(order + "H", head[18:20])[0]


def sdk_path(dji_sdk: str | os.PathLike | None) -> str | None:
    """The SDK library to use: ``dji_sdk`` when given, else ``$THERMOGRAMMETRY_DJI_TSDK``, else None."""
    p = dji_sdk if dji_sdk not in (None, "") else os.environ.get(SDK_ENV) or None
    return None if p is None else str(p)


def _refuse(path, what: str) -> ConfigError:
    return ConfigError(f"DJI Thermal SDK library {str(path)!r}: {what}; {INSTALL_HINT}")


def check_dji_sdk(path: str | os.PathLike) -> Path:
    """Refuse a ``--dji-sdk`` path that cannot be DJI's libdirp for this machine, before any file is read.

    Returns the path; raises :class:`ConfigError` (the path, what is wrong, what to install) when it is missing or a
    folder, not an ELF shared library (on Linux), an ELF of another architecture or word size, or a library
    that does not export ``dirp_create_from_rjpeg`` (checked by loading it, after its plugins).
    """
    p = Path(path)
    if not p.exists():
        raise _refuse(path, "does not exist")
    if p.is_dir():
        lib = p / "libdirp.so"
        hint = f" (the folder holds {lib.name}: give {lib})" if lib.is_file() else ""
        raise _refuse(path, f"is a folder, expected the library file libdirp.so itself{hint}")
    if sys.platform.startswith("linux"):
        try:
            elf = elf_machine(p)
        except OSError as exc:
            raise _refuse(path, f"cannot be read ({exc.strerror or exc})") from None
        if elf is None:
            with open(p, "rb") as fh:
                magic = fh.read(2)
            what = "a Windows DLL, not a Linux shared library" if magic == b"MZ" else "not an ELF shared library"
            raise _refuse(path, what)
        cls, em = elf
        code, name = machine_code()
        bits = 8 * struct.calcsize("P")
        if code is not None and em != code:
            raise _refuse(path, f"is a library for {_NAMES.get(em, f'ELF machine {em}')}, this machine is {name}")
        if cls != (2 if bits == 64 else 1):
            raise _refuse(path, f"is a {32 if cls == 1 else 64}-bit library, this Python is {bits}-bit")
    lib = load_dji_sdk(p)
    if not hasattr(lib, "dirp_create_from_rjpeg"):
        raise _refuse(path, "does not export dirp_create_from_rjpeg: not DJI's libdirp")
    return p


def _preload(folder: Path, target: Path) -> list[str]:
    """Load the SDK folder's plugins and their dependencies with RTLD_GLOBAL, retrying those that fail (one may
    need another) until a pass loads none more. Returns the names loaded; the others are left to libdirp."""
    cands = sorted(q for q in folder.iterdir()
                   if q.name.startswith(PRELOAD_PREFIXES) and ".so" in q.name and q.is_file()
                   and q.resolve() != target.resolve())
    loaded: list[str] = []
    pending = cands
    while pending:
        failed = []
        for q in pending:
            try:
                ctypes.CDLL(str(q), mode=ctypes.RTLD_GLOBAL)
                loaded.append(q.name)
            except OSError:
                failed.append(q)
        if len(failed) == len(pending):
            break
        pending = failed
    return loaded


def load_dji_sdk(path: str | os.PathLike) -> ctypes.CDLL:
    """DJI's ``libdirp`` at ``path``, its folder's plugins loaded first (see the module docstring); one load per
    path and process.

    Raises
    ------
    ConfigError
        The library (or a library it needs) cannot be loaded; names the path and what to install.
    """
    p = Path(path)
    key = str(p.resolve()) if p.exists() else str(p)
    with _LOCK:
        if key in _LOADED:
            return _LOADED[key]
        if not p.is_file():
            raise _refuse(path, "does not exist" if not p.exists() else "is not a file")
        if sys.platform.startswith("linux"):
            try:
                _preload(p.resolve().parent, p)
            except OSError:
                pass
        try:
            lib = ctypes.CDLL(str(p), mode=ctypes.RTLD_GLOBAL)
        except OSError as exc:
            raise _refuse(path, f"cannot be loaded ({exc})") from None
        _LOADED[key] = lib
        return lib
