"""cloudgraph: physically based rendering of participating media from a graph radiance cache.

Importing the package finds Debian's libLLVM 19 for Dr.Jit's LLVM backend (the LLVM 15 that
bookworm ships by default crashes Dr.Jit 1.x with mitsuba 3.9), so that nobody has to set
``DRJIT_LIBLLVM_PATH`` by hand. No Mitsuba variant is chosen here: entry points call
:func:`cloudgraph.mitsuba_scene.set_variant`.
"""

import glob
import os

__version__ = "0.1.0"

#: Bumped whenever the meaning of a cache key or of an on-disk file changes.
ENGINE_FORMAT_VERSION = 7


def _find_libllvm() -> str | None:
    """Newest libLLVM >= 16 on the system, or None."""
    for major in (21, 20, 19, 18, 17, 16):
        for pattern in (
            f"/usr/lib/x86_64-linux-gnu/libLLVM-{major}.so",
            f"/usr/lib/*-linux-gnu/libLLVM-{major}.so",
            f"/usr/lib/llvm-{major}/lib/libLLVM*.so*",
        ):
            hits = sorted(glob.glob(pattern))
            if hits:
                return hits[0]
    return None


if "DRJIT_LIBLLVM_PATH" not in os.environ:
    _lib = _find_libllvm()
    if _lib:
        os.environ["DRJIT_LIBLLVM_PATH"] = _lib
