"""The mesh layer's compiled kernels (``pipeline/mesh/_native.c``, built at install where a C compiler is:
``pyproject.toml``), or ``None`` where they were not built. Each kernel computes what a NumPy function of this
package computes, with the same result (tests/test_native.py compares them); the callers use the kernel when
there is one and the NumPy function otherwise (and for a test, with ``kernels`` set to ``None``)."""

try:
    from scanreg.mesh import _native as kernels
except ImportError:  # no compiler at install: the NumPy versions
    kernels = None
