"""Builds estim's native kernels (estim/forward/_kernels.cc, XLA FFI handlers) against the XLA FFI
headers that jaxlib ships. Everything else about the package is in pyproject.toml."""

import os

import jaxlib
from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "estim.forward._kernels",
            sources=["estim/forward/_kernels.cc"],
            include_dirs=[os.path.join(os.path.dirname(jaxlib.__file__), "include")],
            language="c++",
            # -fno-math-errno and -fno-trapping-math change no result (no errno, no floating-
            # point traps to keep): they let the compiler vectorise the contact search.
            # -ffp-contract=off: no multiply-add fused into an FMA, so that the builds of a loop
            # for AVX2 and AVX-512 (ESTIM_TARGET_CLONES) compute the same bits as the baseline.
            extra_compile_args=["-std=c++17", "-O3", "-fno-math-errno", "-fno-trapping-math", "-ffp-contract=off",
                                "-fvisibility=hidden", "-Wno-attributes", "-Wno-return-type"],
            # Without a C++ compiler estim still installs, and runs the same solver in JAX.
            optional=True,
        )
    ]
)
