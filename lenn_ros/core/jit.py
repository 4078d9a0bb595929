"""Whether numba compiles here, and the ``njit`` every compiled module of the package decorates with.

One place decides it for the kernels (``learning_rules``, ``term_kernels``, ``batch_kernels``), the
compiled live step (``online_step``) and the plants' formulas (``paper.plants``). Without numba the
same functions run as plain Python (``COMPILED`` is then False); with ``NUMBA_DISABLE_JIT=1`` numba is
importable but compiles nothing (``JIT`` is then False). ``test_core`` and ``test_bench`` check that
the compiled and the Python paths give the same numbers.

Conventions of the compiled modules:
- The ``_`` helpers a kernel is split into are ``inline="always"``: numba copies
  them into the kernel, within a few percent of one long loop (a plain call cost up
  to 25% on small networks). A kernel's ``.py_func`` still calls their compiled versions.
- ``cache=True`` keeps the compiled code on disk, and numba checks it against the file a function
  is defined in only: a kernel that calls or inlines a helper of another module (``batch_kernels``
  reads ``term_kernels``' term plan; ``online_step`` the learning rules) keeps its cached code when
  only the helper's file changes. After editing one of them, delete the ``__pycache__`` of
  ``lenn_ros/core`` (its ``*.nbi`` / ``*.nbc`` files).
"""

from __future__ import annotations

try:  # numba is a declared dependency; the fallback keeps the core importable anyway
    from numba import njit

    COMPILED = True
except ImportError:  # pragma: no cover - exercised only where numba is missing
    COMPILED = False

    def njit(*args, **kwargs):  # type: ignore[no-redef]
        def wrap(function):
            function.py_func = function
            return function

        return wrap(args[0]) if args and callable(args[0]) else wrap


#: numba is importable *and* compiling (``NUMBA_DISABLE_JIT=1`` runs every kernel as
#: Python): callers pick a vectorised numpy path over a kernel only when it is not.
try:
    from numba import config as _numba_config

    JIT = COMPILED and not _numba_config.DISABLE_JIT
except ImportError:  # pragma: no cover - exercised only where numba is missing
    JIT = False
