"""Where qtl's compiled kernels live: their sources (every `*.c` here, one shared library), flags and cache key."""

from __future__ import annotations

import hashlib
import platform
from pathlib import Path

DIRECTORY = Path(__file__).parent
# All C sources of this directory, compiled together into one shared library (exp sums, moments, ...).
SOURCES = tuple(sorted(DIRECTORY.glob("*.c")))
COMPILER = "gcc"
# -O3 and -march=native let gcc vectorise the exp loops through libmvec (AVX-512 or AVX2 variants);
# -fno-math-errno lets it call them; -fopenmp for the threads and the `omp simd` reductions.
FLAGS = ("-O3", "-march=native", "-fno-math-errno", "-fopenmp", "-fPIC", "-shared", "-Wall", "-Wextra")
LIBS = ("-lm",)
ARTEFACT_PREFIX = "_qtl_kernels-"


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
    for part in (COMPILER, *FLAGS, *LIBS, cpu_tag()):
        digest.update(b"\0" + part.encode())
    return digest.hexdigest()[:16]


def artefact_path() -> Path:
    """The shared library built from these sources with these flags on this CPU (it may not exist)."""
    return DIRECTORY / f"{ARTEFACT_PREFIX}{cache_key()}.so"
