"""Test-wide set-up that must happen before any test module imports torch or numba."""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # see station/__init__.py
