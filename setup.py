"""Build of the optional fused CPU kernels (swiftjax/align/_ffi_kernels.cc); metadata is in pyproject.toml.

The extension is optional: without a C++17 compiler the install still succeeds and
swiftjax.align uses its pure-JAX formulation (swiftjax/align/_kernels.py).
"""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "swiftjax.align._ffi_kernels",
            sources=["swiftjax/align/_ffi_kernels.cc"],
            depends=["swiftjax/align/_ffi_kernels_loops.inc"],
            include_dirs=["third_party"],
            language="c++",
            extra_compile_args=["-O3", "-std=c++17", "-ffp-contract=off", "-fvisibility=hidden", "-w"],
            optional=True,
        )
    ]
)
