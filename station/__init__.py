"""station: turntable capture-to-asset with Noise Guided Splatting."""

import os

# torch and numba each bring an OpenMP pool; with the default active wait, idle threads of one spin
# while the other works, and small torch ops (an Adam step) run many times slower. Must precede their import.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
