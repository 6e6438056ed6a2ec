"""The test session computes in float64, as the library is specified (tasks.md §0).

Importing pipps does not switch JAX's 64-bit mode on; the session does, before any test module
is imported. tests/test_imports.py checks, in fresh interpreters, what happens without it.
"""

import pipps

pipps.enable_float64()
