"""The training methods and presets by name, and the rule for a preset's safer twin, without the configs.

The batch runner and `station batch run` only check and pass these names on; the configs themselves
(station/ngs/presets.py) import the trainer and with it torch, seconds that every runner start paid
for nothing: its stage processes build the config.
"""

from __future__ import annotations

from station.errors import BadInputError

METHODS = ("3dgs", "alpha", "ngs")
PRESET_NAMES = ("paper", "fast", "tiny")  # the keys of station.ngs.presets.PRESETS
SAFER_SUFFIX = "-safe"  # "fast-safe": the retry of a "fast" run that diverged or ran out of memory


def safer_preset(preset: str) -> str:
    """The preset to retry `preset` with; a safer preset is its own retry."""
    return preset if preset.endswith(SAFER_SUFFIX) else preset + SAFER_SUFFIX


def check_names(method: str, preset: str) -> None:
    """Refuse an unknown method or preset (BadInputError) before any work is done with it."""
    if method not in METHODS:
        raise BadInputError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    if preset.removesuffix(SAFER_SUFFIX) not in PRESET_NAMES:
        raise BadInputError(f"unknown preset {preset!r}; choose one of {', '.join(PRESET_NAMES)} "
                            f"(or NAME{SAFER_SUFFIX})")
