"""The training resolution schedule: start coarse, move up once the scene's held-out error says so.

The first steps place and grow Gaussians, and a coarse image does that for a quarter of the pixel
cost. A model fitted only to coarse images renders thin, aliased Gaussians at full resolution,
though, so training always ends at full resolution, and the question a scene answers is when to move up. At each check the
held-out views are scored at full resolution; while the coarse level still raises that score,
training stays coarse, and once it stops rising the downscale halves. No level lasts longer than
splatfacto's fixed schedule (3,000 of 30,000 steps per level). Every check, with its figures, goes
into train_metrics.json.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from station.errors import BadInputError


@dataclass
class ResolutionConfig:
    start_downscale: int = 1  # 1: full resolution throughout; otherwise a power of two
    check_every: float = 1_000 / 30_000  # fraction of the run between checks while coarse
    max_level_steps: float = 3_000 / 30_000  # fraction of the run any coarse level may last
    min_psnr_gain_db: float = 0.1  # per check, at full resolution: a smaller gain means the level stopped paying

    def __post_init__(self) -> None:
        if self.start_downscale < 1 or self.start_downscale & (self.start_downscale - 1):
            raise BadInputError(f"resolution start_downscale must be a power of two >= 1, got {self.start_downscale}")

    def check_steps(self, total_steps: int) -> int:
        """Steps between checks in a run `total_steps` long."""
        return max(1, round(self.check_every * total_steps))

    def level_limit(self, total_steps: int) -> int:
        """The most steps a coarse level may last in a run `total_steps` long."""
        return max(1, round(self.max_level_steps * total_steps))


def resolution_decision(cfg: ResolutionConfig, checks_at_level: list[dict], level_steps: int, max_level_steps: int) -> dict:
    """Whether to halve the training downscale, from the full-resolution held-out PSNR of this level's checks
    (oldest first; the last one is now) and the steps trained at this level so far."""
    last = checks_at_level[-1]
    decision = {**last, "move_up": True}
    if math.isnan(last["psnr"]):
        return {**decision, "reason": "no held-out views to judge by"}
    if level_steps >= max_level_steps:
        return {**decision, "reason": f"{level_steps} steps at this level, the most any level may last"}
    if len(checks_at_level) < 2:
        return {**decision, "move_up": False, "reason": "first check at this level"}
    gain = last["psnr"] - checks_at_level[-2]["psnr"]
    decision["psnr_gain_db"] = round(gain, 4)
    if gain < cfg.min_psnr_gain_db:
        return {**decision, "reason": f"held-out PSNR at full resolution gained {gain:+.2f} dB: this level stopped paying"}
    return {**decision, "move_up": False, "reason": f"held-out PSNR at full resolution still rising ({gain:+.2f} dB)"}
