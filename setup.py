"""Only the optional C fast path lives here; everything else is in pyproject.toml.

``optional=True``: where no compiler is at hand the install still succeeds and the bus runs its
pure-Python twin of the same code (protocol/fastpath.py says which one is in use)."""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "protocol._fastpath",
            ["protocol/_fastpath.c"],
            optional=True,
            extra_compile_args=["-O3", "-Wall", "-Wextra", "-Wno-unused-parameter"],
        )
    ]
)
