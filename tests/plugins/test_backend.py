"""libLLVM resolution order and the refusal message (mi_plugins.backend)."""

import os

import numpy as np

import pytest

from conftest import CUDA
from mi_plugins import backend as bk


def _lib(folder, name):
    folder.mkdir(parents=True, exist_ok=True)
    p = folder / name
    p.write_bytes(b"\x7fELF")
    return str(p)


def test_version_parsing():
    assert bk.llvm_major("/x/libLLVM-15.so") == 15
    assert bk.llvm_major("/x/libLLVM-14.0.6.so.1") == 14
    assert bk.llvm_major("/x/libLLVM.so.23.1") == 23
    assert bk.llvm_major("/x/libLLVM.so.19.1") == 19
    assert bk.llvm_major("/x/libLLVM-19.so") == 19


def test_env_variable_wins(tmp_path):
    env_lib = _lib(tmp_path / "env", "libLLVM.so.20.1")
    venv = _lib(tmp_path / "venv", "libLLVM.so.23.1")
    choice = bk.resolve_libllvm({bk.ENV_LLVM: env_lib}, [os.path.dirname(venv)], [])
    assert choice == bk.LLVMChoice(env_lib, "env", 20)


def test_env_variable_naming_llvm15_is_refused(tmp_path):
    old = _lib(tmp_path, "libLLVM-15.so")
    with pytest.raises(bk.LLVMVersionError, match="fminimum"):
        bk.resolve_libllvm({bk.ENV_LLVM: old}, [], [])


def test_env_variable_naming_missing_file(tmp_path):
    with pytest.raises(bk.LLVMVersionError, match="no such file"):
        bk.resolve_libllvm({bk.ENV_LLVM: str(tmp_path / "nope.so")}, [], [])


def test_venv_before_system(tmp_path):
    venv = _lib(tmp_path / "venv" / "lib", "libLLVM.so.23.1")
    _lib(tmp_path / "sys", "libLLVM-19.so")
    choice = bk.resolve_libllvm({}, [str(tmp_path / "venv" / "lib")], [str(tmp_path / "sys")])
    assert choice == bk.LLVMChoice(venv, "venv", 23)


def test_system_newest_usable_and_old_ones_skipped(tmp_path):
    sysdir = tmp_path / "sys"
    _lib(sysdir, "libLLVM-14.so")
    _lib(sysdir, "libLLVM-15.so")
    new = _lib(sysdir, "libLLVM-19.so")
    _lib(sysdir, "libLLVM-17.so")
    choice = bk.resolve_libllvm({}, [str(tmp_path / "emptyvenv")], [str(sysdir)])
    assert choice == bk.LLVMChoice(new, "system", 19)


def test_only_old_llvm_gives_message_with_why_and_fix(tmp_path):
    sysdir = tmp_path / "sys"
    _lib(sysdir, "libLLVM-14.so")
    _lib(sysdir, "libLLVM-15.so")
    with pytest.raises(bk.LLVMVersionError) as err:
        bk.resolve_libllvm({}, [], [str(sysdir)])
    msg = str(err.value)
    assert "libLLVM 15" in msg and "libLLVM-15.so" in msg  # names the newest too-old library
    assert "Cannot select" in msg and "fminimum" in msg  # why
    assert "karellen-llvm-core" in msg and "libllvm19" in msg and bk.ENV_LLVM in msg  # how to fix


def test_nothing_found_sets_nothing(tmp_path):
    assert bk.resolve_libllvm({}, [str(tmp_path)], [str(tmp_path)]) == bk.LLVMChoice(None, "none", None)


def test_this_environment_resolves_a_usable_llvm():
    # The project installs karellen-llvm-core, so the venv always has one.
    choice = bk.resolve_libllvm({})
    assert choice.path and choice.major >= bk.MIN_LLVM_MAJOR


def test_variant_override_and_validation(monkeypatch):
    assert bk.choose_variant({bk.ENV_VARIANT: "llvm_ad_rgb"}) == "llvm_ad_rgb"
    with pytest.raises(bk.VariantError, match="PHOTOREAL_VARIANT='cuda_magic_rgb' is not a Mitsuba variant"):
        bk.choose_variant({bk.ENV_VARIANT: "cuda_magic_rgb"})
    # variants photoreal's plugins cannot run on are refused up front, with the reason
    for v in ("scalar_rgb", "llvm_ad_mono"):
        with pytest.raises(bk.VariantError, match="RGB variant with automatic differentiation"):
            bk.choose_variant({bk.ENV_VARIANT: v})
    monkeypatch.setattr(bk, "cuda_works", lambda: False)
    with pytest.raises(bk.VariantError, match="no CUDA device"):
        bk.choose_variant({bk.ENV_VARIANT: "cuda_ad_rgb"})


def test_variant_default_follows_cuda_probe(monkeypatch):
    monkeypatch.setattr(bk, "cuda_works", lambda: False)
    assert bk.choose_variant({}) == "llvm_ad_rgb"
    monkeypatch.setattr(bk, "cuda_works", lambda: True)
    assert bk.choose_variant({}) == "cuda_ad_rgb"


def test_already_loaded_old_llvm_is_reported_not_aborted(tmp_path):
    maps = tmp_path / "maps"
    maps.write_text("7f00-7f01 r-xp 00000000 08:01 1 /usr/lib/x86_64-linux-gnu/libLLVM-15.so.1\n"
                    "7f02-7f03 r-xp 00000000 08:01 2 /usr/lib/libc.so.6\n")
    assert bk.loaded_libllvm(str(maps)) == ["/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1"]
    with pytest.raises(bk.LLVMVersionError, match="imported before mi_plugins"):
        bk.check_loaded_libllvm(str(maps))
    maps.write_text("7f00-7f01 r-xp 00000000 08:01 1 /venv/lib/libLLVM.so.23.1\n")
    bk.check_loaded_libllvm(str(maps))  # fine


def test_venv_interpreter_finds_llvm_even_when_mitsuba_is_imported_first():
    # `make install` writes a .pth that exports DRJIT_LIBLLVM_PATH at interpreter start-up,
    # so `import mitsuba` before `import mi_plugins` does not load the system's LLVM 15.
    import subprocess
    import sys

    code = ("import drjit as dr, mitsuba as mi; mi.set_variant('llvm_ad_rgb'); "
            "x = dr.llvm.ad.Float([1, 2, 3]); print(float(dr.sum(dr.minimum(dr.maximum(x, 0.5), 2.5))[0]))")
    env = {k: v for k, v in __import__("os").environ.items() if k != bk.ENV_LLVM}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "5.5"


@pytest.mark.skipif(CUDA, reason="an LLVM-backend property: CUDA copies host arrays to the GPU")
def test_unaligned_host_arrays_compile_kernels_of_their_own_and_aligned_copies_do_not():
    # Dr.Jit maps a numpy array zero-copy and compiles unaligned inputs with unaligned loads, i.e. as
    # a different kernel (mi_plugins/arrays.py). The oracle is Dr.Jit's own kernel history: the same
    # computation on a 16-byte-offset view runs another kernel; aligned() copies of it run the first.
    import drjit as dr
    import mitsuba as mi
    from conftest import compiled_kernels
    from mi_plugins.arrays import ALIGN, aligned, is_aligned

    buf = aligned(np.random.default_rng(0).random(1040))
    a, b = buf[:1000], buf[4:1004]  # 16 bytes apart: b is not on a 32-byte boundary
    assert is_aligned(a) and not is_aligned(b) and aligned(a) is a
    c = aligned(b)
    assert is_aligned(c) and c.ctypes.data % ALIGN == 0 and np.array_equal(c, b)
    assert aligned(b[::2]).flags.c_contiguous and np.array_equal(aligned(b[::2]), b[::2])
    assert aligned(np.arange(5), np.uint32).dtype == np.uint32 and aligned(b, None).dtype == b.dtype

    def run(x):
        with compiled_kernels() as k:
            dr.eval(mi.Float(x) * 2.0 + 1.0)
        return k.hashes[-1], "".join(k.irs)

    h_a, _ = run(a)
    h_b, ir_b = run(b)
    h_c, _ = run(c)
    assert h_b != h_a and (ir_b == "" or "align 1," in ir_b)  # compiled now, or found in the disk cache
    assert h_c == h_a
