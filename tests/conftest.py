"""The test session computes in float64, as the library is specified.

Importing pipps does not switch JAX's 64-bit mode on; the session does, before any test module
is imported. tests/test_imports.py checks, in fresh interpreters, what happens without it.

After each test module the session drops the compiled programs it holds
(:func:`pipps.experiments.sweep.release_compiled`), as a sweep does after each experiment: every
cached program keeps its own memory mappings, and one pytest process over the whole suite used to
crash in native code near its end, the pattern of a process at Linux's mapping limit
(``vm.max_map_count``, 65,530). Modules rarely share programs, so little is compiled twice. With
``PIPPS_TEST_MAPS=FILE`` the session appends, per module, the process's mapping count before and
after the release to FILE, with the xdist worker that ran it (``main`` without xdist; README,
"Quick start", quotes a one-process record).
"""

import os

import pytest

import pipps

pipps.enable_float64()

_MAPS_LOG = os.path.abspath(os.environ["PIPPS_TEST_MAPS"]) if os.environ.get("PIPPS_TEST_MAPS") else None


def _mappings() -> int:
    try:
        with open("/proc/self/maps") as f:
            return sum(1 for _ in f)
    except OSError:  # not Linux
        return -1


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_after_module(request):
    yield
    from pipps.experiments.sweep import release_compiled

    before = _mappings()
    release_compiled()
    if _MAPS_LOG:
        with open(_MAPS_LOG, "a") as f:
            worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
            f.write(f"{request.node.nodeid}\t{worker}\t{before}\t{_mappings()}\n")
