"""Where qtl's compiled kernels live: their sources (every `*.c` here, one library), compiler, flags and cache."""

from __future__ import annotations

import hashlib
import os
import platform
import shlex
from pathlib import Path

DIRECTORY = Path(__file__).parent
# All C sources of this directory, compiled together into one shared library (exp sums, moments, ...).
SOURCES = tuple(sorted(DIRECTORY.glob("*.c")))
# The compiler when the `CC` environment variable names none.
COMPILER = "gcc"
# -O3 and -march=native let gcc vectorise the exp loops through libmvec (AVX-512 or AVX2 variants);
# -fno-math-errno lets it call them; -fopenmp for the threads and the `omp simd` reductions.
FLAGS = ("-O3", "-march=native", "-fno-math-errno", "-fopenmp", "-fPIC", "-shared", "-Wall", "-Wextra")
LIBS = ("-lm",)
ARTEFACT_PREFIX = "_qtl_kernels-"
# The environment variable that overrides the cache root (`$XDG_CACHE_HOME/qtl`, else `~/.cache/qtl`).
CACHE_ENV = "QTL_CACHE_DIR"


def compiler() -> tuple[str, ...]:
    """The C compiler's command: ``$CC`` (split like a shell word list) when set, else :data:`COMPILER`."""
    return tuple(shlex.split(os.environ.get("CC", ""))) or (COMPILER,)


def cache_root() -> Path:
    """qtl's per-user cache: ``$QTL_CACHE_DIR``, else ``$XDG_CACHE_HOME/qtl``, else ``~/.cache/qtl``."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV]).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg and Path(xdg).is_absolute() else Path.home() / ".cache") / "qtl"


def cache_directory() -> Path:
    """The directory of the compiled kernels (and of the lock that lets one process at a time compile them)."""
    return cache_root() / "native"


def cpu_tag() -> str:
    """What `-march=native` compiled for: the machine and its CPU feature flags (Linux), else the machine."""
    tag = platform.machine()
    try:
        with open("/proc/cpuinfo") as info:
            for line in info:
                if line.startswith("flags"):
                    return tag + ":" + " ".join(sorted(line.split(":", 1)[1].split()))
    except OSError:
        pass
    return tag + ":" + platform.processor()


def cache_key() -> str:
    """A hash of the sources, the compiler and its flags, and the CPU: a new key means a rebuild."""
    digest = hashlib.sha256()
    for source in SOURCES:
        digest.update(source.name.encode() + b"\0" + source.read_bytes())
    for part in (*compiler(), *FLAGS, *LIBS, cpu_tag()):
        digest.update(b"\0" + part.encode())
    return digest.hexdigest()[:16]


def artefact_path() -> Path:
    """The shared library built from these sources with this compiler and flags on this CPU (it may not exist)."""
    return cache_directory() / f"{ARTEFACT_PREFIX}{cache_key()}.so"
