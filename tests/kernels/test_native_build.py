"""The native kernel's build: cached by source, compiler, flags and CPU; a failed build leaves the torch path."""

from __future__ import annotations

import platform
import shutil

import pytest

from qtl.kernels.native import artefact
from qtl.kernels.native import build as native_build
from qtl.kernels.native.exp_sum import ExpSumLibrary
from qtl.kernels.native.loader import open_library


def test_a_second_build_is_a_cache_hit(built):
    stamp = built.stat().st_mtime_ns
    assert native_build.build() == built
    assert built.stat().st_mtime_ns == stamp
    assert built.parent == artefact.cache_directory() and built.name.startswith(artefact.ARTEFACT_PREFIX)


def test_the_cache_key_follows_source_flags_and_cpu(monkeypatch, tmp_path):
    key, original = artefact.cache_key(), artefact.DIRECTORY / "exp_sum.c"
    source = tmp_path / "exp_sum.c"
    shutil.copy(original, source)
    monkeypatch.setattr(artefact, "SOURCES", tuple(source if s == original else s for s in artefact.SOURCES))
    assert artefact.cache_key() == key
    source.write_text(source.read_text() + "\n/* changed */\n")
    assert artefact.cache_key() != key
    shutil.copy(original, source)
    monkeypatch.setattr(artefact, "FLAGS", (*artefact.FLAGS, "-DSOMETHING"))
    assert artefact.cache_key() != key
    monkeypatch.setattr(artefact, "FLAGS", artefact.FLAGS[:-1])
    monkeypatch.setattr(artefact, "cpu_tag", lambda: "another-cpu")
    assert artefact.cache_key() != key
    monkeypatch.undo()
    monkeypatch.setenv("CC", "clang -fsomething")
    assert artefact.compiler() == ("clang", "-fsomething") and artefact.cache_key() != key


def test_the_cache_root_follows_qtl_cache_dir_then_xdg_then_home(monkeypatch, tmp_path):
    monkeypatch.delenv("QTL_CACHE_DIR", raising=False)
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert artefact.cache_directory() == tmp_path / "home" / ".cache" / "qtl" / "native"
    monkeypatch.setenv("XDG_CACHE_HOME", "relative/ignored")  # the XDG spec: a relative path is ignored
    assert artefact.cache_root() == tmp_path / "home" / ".cache" / "qtl"
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert artefact.cache_root() == tmp_path / "xdg" / "qtl"
    monkeypatch.setenv("QTL_CACHE_DIR", str(tmp_path / "mine"))
    assert artefact.artefact_path().parent == tmp_path / "mine" / "native"


def test_a_failed_build_keeps_the_kernel_and_says_torch_once(built, monkeypatch, capsys):
    monkeypatch.setattr(native_build, "compiler", lambda: ("/nonexistent/cc",))  # the same key: a forced rebuild
    assert native_build.main(["--force", "--optional"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "torch path" in err[0] and "/nonexistent/cc" in err[0] and "install gcc" in err[0]
    assert native_build.main(["--force"]) == 1
    assert built.is_file()  # the cached kernel is untouched by a failed rebuild


# The kernel's vector width follows the CPU it is compiled for: AVX-512 (8 doubles), AVX (4) or
# the baseline ISA (2). The build machine has one of them; compile the narrower ones on purpose.
NARROWER = {
    "baseline": lambda flags: tuple(f for f in flags if f != "-march=native"),
    "avx2": lambda flags: (*flags, "-mno-avx512f"),
}


@pytest.mark.parametrize("isa", sorted(NARROWER))
def test_narrower_vector_builds_agree_with_torch(built, isa, monkeypatch, tmp_path):
    if isa == "avx2" and platform.machine() not in ("x86_64", "AMD64"):
        pytest.skip("-mno-avx512f is an x86-64 flag")
    monkeypatch.setattr(native_build, "FLAGS", NARROWER[isa](native_build.FLAGS))
    target = tmp_path / f"exp_sum_{isa}.so"
    native_build.compile_kernel(target)
    native_build.check_against_torch(ExpSumLibrary(open_library(target)))  # raises BuildError when it disagrees
