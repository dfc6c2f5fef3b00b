"""How much view-dependent colour to keep: the lowest SH degree the scene's held-out views need.

A stone on a softbox shows little view-dependent colour, so the higher SH bands fit little but
noise and make the splat files up to four times larger. After training, held-out PSNR is
measured with the colour cut to each degree; the lowest degree within `tolerance_db` of the
trained one is written, and the figures go into train_metrics.json.
"""

from __future__ import annotations

import math
from typing import Callable

import torch

from station.ngs.gaussians import num_sh_bases


def sh_degree_choice(trained_degree: int, trained_psnr: float, held_out_psnr: Callable[[int], float],
                     tolerance_db: float) -> dict:
    """{"trained", "kept", "tolerance_db", "held_out_psnr": {degree: dB}}; `held_out_psnr` is asked only for
    the degrees below the trained one. Kept is the trained degree when nothing is held out (NaN)."""
    if math.isnan(trained_psnr):
        psnr = {trained_degree: trained_psnr}
    else:
        psnr = {**{degree: held_out_psnr(degree) for degree in range(trained_degree)}, trained_degree: trained_psnr}
    kept = min(d for d, value in psnr.items() if d == trained_degree or value >= trained_psnr - tolerance_db)
    return {"trained": trained_degree, "kept": kept, "tolerance_db": tolerance_db,
            "held_out_psnr": {str(d): round(value, 3) for d, value in psnr.items()}}


def cut_to_degree(params: dict[str, torch.Tensor], degree: int) -> dict[str, torch.Tensor]:
    """The same Gaussians with their colour cut to SH `degree` (the higher bands dropped)."""
    return {**params, "shN": params["shN"][:, : num_sh_bases(degree) - 1].clone()}
