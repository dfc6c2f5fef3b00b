"""Turntable drivers (GRBL 1.1 / grblHAL over pyserial)."""
