"""The optional compiled core (runtime/native, issue 49): everything else is in pyproject.toml.

``pip install .`` compiles the core's C files (runtime/native/dimenet_*.c) and the binding (_module*.c)
into dimenet.runtime.native._core.
Where no C compiler works, the build prints one warning and installs the pure-numpy package, which
runs the same stages (dimenet.runtime.native says which one runs; ``dimenet --version`` prints it).
"""

import sys
from glob import glob

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext
from setuptools.errors import CCompilerError, CompileError, ExecError, LinkError, PlatformError

BUILD_ERRORS = (CCompilerError, CompileError, ExecError, LinkError, PlatformError, OSError)
# C99, and no fused multiply-add: the numpy reference rounds every product (dimenet_core.h).
UNIX_FLAGS = ["-std=c99", "-ffp-contract=off"]


class OptionalBuildExt(build_ext):
    """build_ext that warns once and carries on without the extension when it cannot be compiled."""

    warned = False

    def _skip(self, exc: BaseException) -> None:
        if not OptionalBuildExt.warned:
            OptionalBuildExt.warned = True
            print(
                f"WARNING: dimenet's compiled core was not built ({type(exc).__name__}: {exc}); "
                "the pure-numpy implementation is installed (slower feature stage, same results)",
                file=sys.stderr,
            )

    def run(self) -> None:
        try:
            super().run()
        except BUILD_ERRORS as exc:
            self._skip(exc)

    def build_extension(self, ext) -> None:
        if self.compiler.compiler_type in ("unix", "mingw32", "cygwin"):
            ext.extra_compile_args = [*UNIX_FLAGS, *(a for a in ext.extra_compile_args if a not in UNIX_FLAGS)]
        try:
            super().build_extension(ext)
        except BUILD_ERRORS as exc:
            self._skip(exc)


setup(
    ext_modules=[
        Extension(
            "dimenet.runtime.native._core",
            sources=[*sorted(glob("runtime/native/dimenet_*.c")), *sorted(glob("runtime/native/_module*.c"))],
            depends=sorted(glob("runtime/native/*.h")),
            include_dirs=["runtime/native"],
        )
    ],
    cmdclass={"build_ext": OptionalBuildExt},
)
