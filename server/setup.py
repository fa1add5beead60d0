"""The compiled part of the server package: the fused merge loops (renderfarm/_kernels.c).
Everything else is declared in pyproject.toml."""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "renderfarm._kernels",
            ["renderfarm/_kernels.c"],
            # -fno-math-errno lets the compiler vectorise sqrt; no other math relaxation.
            extra_compile_args=["-fno-math-errno", "-Wall", "-Wextra", "-Werror"],
        )
    ]
)
