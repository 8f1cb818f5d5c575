"""Choose the Mitsuba variant and make sure Dr.Jit finds a usable LLVM.

Dr.Jit's CPU backend loads ``libLLVM.so`` at run time. Dr.Jit 1.5 refuses
LLVM older than 15 and aborts with "Cannot select ... fminimum" on LLVM 15,
so we look for LLVM >= 19 ourselves *before* Dr.Jit is imported and point
``DRJIT_LIBLLVM_PATH`` at it. When none is found we stop with one line
that names the fix, instead of a crash deep inside the JIT.
"""

from __future__ import annotations

import glob
import os
import re
import sys
import warnings

from .errors import UserError

#: Oldest LLVM release known to work with Dr.Jit 1.5 on this code.
MIN_LLVM = 19

#: Where Debian, Ubuntu, Fedora and conda put the LLVM shared library.
LLVM_SEARCH_GLOBS = (
    "/usr/lib/x86_64-linux-gnu/libLLVM*.so*",
    "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/lib64/libLLVM*.so*",
    "/usr/lib/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
    "/opt/homebrew/opt/llvm/lib/libLLVM.dylib",
    "/usr/local/opt/llvm/lib/libLLVM.dylib",
)

LLVM_FIX = (
    f"no usable LLVM (>= {MIN_LLVM}) found for Dr.Jit's CPU backend; "
    "install it with 'sudo apt-get install libllvm19' "
    "(or set DRJIT_LIBLLVM_PATH to a libLLVM.so of version >= 19)"
)

VARIANTS = ("llvm_ad_rgb", "cuda_ad_rgb")


#: The LLVM library itself (libLLVM.so.19.1, libLLVM-19.so), not one of its
#: companions such as libLLVMSPIRVLib.so.19.
_LLVM_LIBRARY = re.compile(r"^libLLVM([-.]\d|\.so|\.dylib)")


def _llvm_major(path: str) -> int | None:
    """Major LLVM version encoded in a library file name, e.g. libLLVM-19.so -> 19."""
    name = os.path.basename(os.path.realpath(path))
    m = re.search(r"LLVM[-.]?(\d+)", name) or re.search(r"\.so\.(\d+)", name)
    if m is None:
        m = re.search(r"llvm-(\d+)", path)
    return int(m.group(1)) if m else None


def find_llvm() -> str | None:
    """Path of the newest LLVM shared library with version >= MIN_LLVM, or None."""
    best, best_version = None, -1
    for pattern in LLVM_SEARCH_GLOBS:
        for path in sorted(glob.glob(pattern)):
            if not _LLVM_LIBRARY.match(os.path.basename(path)):
                continue
            version = _llvm_major(path)
            if version is not None and version >= MIN_LLVM and version > best_version:
                best, best_version = path, version
    return best


#: The first bytes of ELF (Linux) and Mach-O (macOS, also universal) shared libraries.
_LIBRARY_MAGIC = (b"\x7fELF", b"\xfe\xed\xfa\xce", b"\xfe\xed\xfa\xcf", b"\xce\xfa\xed\xfe",
                  b"\xcf\xfa\xed\xfe", b"\xca\xfe\xba\xbe")


def _is_shared_library(path: str) -> bool:
    try:
        with open(path, "rb") as f:
            return f.read(4) in _LIBRARY_MAGIC
    except OSError:  # a folder, or unreadable
        return False


def ensure_llvm() -> None:
    """Point Dr.Jit at a usable LLVM, or raise UserError with the fix.

    A user-set ``DRJIT_LIBLLVM_PATH`` is trusted as long as it is a shared
    library whose name does not say it is older than ``MIN_LLVM``.
    """
    user_path = os.environ.get("DRJIT_LIBLLVM_PATH")
    if user_path:
        if not os.path.exists(user_path):
            raise UserError(f"DRJIT_LIBLLVM_PATH={user_path} does not exist; " + LLVM_FIX)
        version = _llvm_major(user_path)
        if version is not None and version < MIN_LLVM:
            raise UserError(f"DRJIT_LIBLLVM_PATH={user_path} is LLVM {version}; " + LLVM_FIX)
        if not _is_shared_library(user_path):  # Dr.Jit would print its loader's errors, then a wrong fix
            raise UserError(f"DRJIT_LIBLLVM_PATH={user_path} is not a shared library; " + LLVM_FIX)
        return
    path = find_llvm()
    if path is None:
        raise UserError(LLVM_FIX)
    os.environ["DRJIT_LIBLLVM_PATH"] = path


def set_variant(name: str | None = None) -> str:
    """Select the Mitsuba variant and return its name.

    ``name`` defaults to ``$MITSUBA_ACTIVE_VARIANT`` or, when a Mitsuba
    variant with autodiff and RGB is already set by the caller's pipeline,
    that one (as it is: no LLVM check); otherwise ``llvm_ad_rgb``. Another
    variant set by the caller (scalar, spectral) is switched, with a warning.
    ``cuda_ad_rgb`` needs a GPU, and no LLVM.
    """
    name = name or os.environ.get("MITSUBA_ACTIVE_VARIANT") or None  # set but empty: unset
    if name is not None and name not in VARIANTS:
        raise UserError(f"unknown variant '{name}'; choose one of {', '.join(VARIANTS)}")
    # Only a Mitsuba the caller already imported can have a variant set.
    loaded = sys.modules.get("mitsuba")
    current = loaded.variant() if loaded is not None else None
    if name is None and current in VARIANTS:
        return current
    name = name or "llvm_ad_rgb"
    if name != "cuda_ad_rgb" and current != name:
        ensure_llvm()
    import mitsuba as mi  # here, not above: Dr.Jit loads only once ensure_llvm() has found LLVM

    if name == "cuda_ad_rgb":
        import drjit as dr  # loaded by Mitsuba's import just above

        if not dr.has_backend(dr.JitBackend.CUDA):
            raise UserError("the cuda_ad_rgb variant needs an NVIDIA GPU with its driver, and none was found; "
                            "unset MITSUBA_ACTIVE_VARIANT to run on the CPU (llvm_ad_rgb)")
    if mi.variant() != name:
        try:
            mi.set_variant(name)
        except Exception as exc:  # e.g. no CUDA driver
            raise UserError(f"cannot use Mitsuba variant '{name}': {exc}") from None
        if current is not None and current not in VARIANTS:
            # The caller's pipeline chose a variant the fields cannot run on
            # (scalar, spectral...): its Mitsuba objects and types stay in that one.
            warnings.warn(f"mitsuba-active switched Mitsuba from variant '{current}' to '{name}' "
                          f"(it needs one of {', '.join(VARIANTS)}); objects made under '{current}' "
                          "do not mix with it", stacklevel=_outside_stacklevel())
    return name


def _outside_stacklevel() -> int:
    """``stacklevel`` of a warning raised by this function's caller that
    names the first line outside this package: the pipeline's line that
    imported the package. (``warnings`` itself passes over the frames of
    Python's import machinery, so only the package's own frames count.)"""
    package = os.path.dirname(os.path.abspath(__file__))
    level, frame = 2, sys._getframe(2)
    while frame is not None:
        name = frame.f_code.co_filename
        if name.startswith(package):
            level += 1
        elif not ("importlib" in name and "_bootstrap" in name):
            break
        frame = frame.f_back
    return level


def require_variant(what: str) -> None:
    """Raise UserError unless Mitsuba runs one of :data:`VARIANTS` (the caller
    may have switched it after importing the package): in another, renders
    would be of another kind (spectral) under the same cache keys, or fail
    deep inside Mitsuba (scalar)."""
    import mitsuba as mi  # here, not above: importing this module must not load Dr.Jit (see ensure_llvm)

    if mi.variant() not in VARIANTS:
        raise UserError(f"{what} needs Mitsuba variant {' or '.join(VARIANTS)}, but '{mi.variant()}' is set; "
                        "call mitsuba_active.set_variant() first")
