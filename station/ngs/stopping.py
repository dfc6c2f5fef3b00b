"""How long to train: the preset's schedule, cut short or extended by the scene's own held-out error.

The NGS phases are fractions of a planned step count, so the plan has to be fixed up front. What a
scene needs shows only as it trains: a small stone on a softbox is opaque well before the fast
preset's 2,500 steps, a larger or shinier one is not yet opaque at the end. So once the NGS phases
are over, a run whose held-out SOS and PSNR are both at their targets, and whose infill shows through
in no held-out view by half an 8-bit level even on one pixel, ends at that evaluation (looked for every
`finish_every` steps too, between the evaluations: the criterion is absolute, not a gain); and after the
plan, training goes on in blocks of `eval_every` steps while SOS is below its target and still
rising, or while held-out PSNR still rises clearly and is below its own target, up to a cap. Every
decision, with the figures behind it, is kept in train_metrics.json.
"""

from __future__ import annotations

from dataclasses import dataclass

BETWEEN_BLOCKS = "between_blocks"  # marks an evaluation made for the early finish alone, between two blocks


@dataclass
class ExtendConfig:
    """How far past its plan a run may train on, and when it may end before it."""

    max_extra_steps: int = 0  # 0: train exactly the planned steps
    sos_target: float = 0.95  # no extension for SOS once the held-out SOS reaches this
    min_sos_gain: float = 0.005  # per block, averaged over `sos_window` blocks: a smaller gain is a plateau
    sos_window: int = 2  # one block's gain is noise (DTU scan65: +0.031, +0.002, +0.035 in a row)
    # Per block. Held-out PSNR wanders between evaluations once it has converged, so only a clear rise counts.
    min_psnr_gain_db: float = 0.25
    psnr_target_db: float = 40.0  # no extension for PSNR above this: further gains are not visible in the asset
    # End before the plan once the NGS phases are over, held-out SOS is at least this, PSNR is at its target and
    # no held-out view shows more than `finish_max_leak_px` of the infill. None: always train the whole plan.
    finish_sos: float | None = None
    # Summed green of the infill showing through, in pixels' worth of full green: half of one 8-bit level even
    # if it all fell on one pixel, so nothing of it can show in the asset. SOS, a log, still rises long after.
    finish_max_leak_px: float = 0.5 / 255
    # Within the plan, once the NGS phases are over, an early end is also looked for every this many steps
    # between the evaluations (0: at the evaluations only). Extensions are still judged on whole blocks.
    finish_every: int = 0


def early_finish_decision(cfg: ExtendConfig, evals: list[dict], phases_over: bool) -> dict | None:
    """The decision to end the run at the last held-out evaluation, before its plan; None to train on."""
    last = evals[-1] if evals else {}
    sos, psnr, leak_px = last.get("sos"), last.get("psnr"), last.get("leak_px")
    if cfg.finish_sos is None or not phases_over or sos is None or psnr is None or leak_px is None:
        return None
    if sos < cfg.finish_sos or not psnr >= cfg.psnr_target_db or leak_px > cfg.finish_max_leak_px:
        return None
    return {"step": last.get("step"), "extend": False, "finished_early": True,
            "reason": f"SOS {_sos(sos, cfg.finish_sos)} reached {cfg.finish_sos:g}, PSNR {psnr:.1f} dB is above "
                      f"{cfg.psnr_target_db:g} "
                      f"and no held-out view shows more than {leak_px:.2g} px of the infill after the NGS phases: "
                      "the rest of the plan would not show in the asset"}


def extension_decision(cfg: ExtendConfig, evals: list[dict], extra_steps_so_far: int, block: int) -> dict:
    """Whether to train one more block, judged on the last held-out evaluations at block ends (the gains are per
    block: the checks between blocks are left out)."""
    evals = [e for e in evals if not e.get(BETWEEN_BLOCKS)]
    last = evals[-1] if evals else {}
    decision = {"step": last.get("step"), "extend": False, "reason": ""}
    if cfg.max_extra_steps <= 0:
        return {**decision, "reason": "extension off"}
    if extra_steps_so_far + block > cfg.max_extra_steps:
        return {**decision, "reason": f"cap of {cfg.max_extra_steps} extra steps reached"}
    if len(evals) < 2:
        return {**decision, "reason": "fewer than two held-out evaluations to compare"}
    before = evals[-2]
    sos, sos_before = last.get("sos"), before.get("sos")
    psnr_gain = last["psnr"] - before["psnr"]
    decision["psnr_gain_db"] = round(psnr_gain, 4)
    if sos is not None and sos_before is not None:
        window = [e["sos"] for e in evals[-1 - cfg.sos_window:] if e.get("sos") is not None]
        decision["sos_gain"] = round(sos - sos_before, 4)
        per_block = (sos - window[0]) / (len(window) - 1)  # what the rule reads
        decision["sos_gain_per_block"] = round(per_block, 4)
        if sos < cfg.sos_target and per_block >= cfg.min_sos_gain:
            return {**decision, "extend": True,
                    "reason": f"SOS {_sos(sos, cfg.sos_target)} below {cfg.sos_target} and still rising"}
    if psnr_gain >= cfg.min_psnr_gain_db and last["psnr"] < cfg.psnr_target_db:
        return {**decision, "extend": True, "reason": f"held-out PSNR still rising ({psnr_gain:+.2f} dB)"}
    above = last["psnr"] >= cfg.psnr_target_db
    psnr = f"PSNR {last['psnr']:.1f} dB above {cfg.psnr_target_db:g}" if above else "PSNR flat"
    return {**decision, "reason": "held-out PSNR and SOS stopped improving" if sos is None or sos < cfg.sos_target
            else f"SOS {_sos(sos, cfg.sos_target)} reached {cfg.sos_target}, {psnr}"}


def _sos(sos: float, target: float) -> str:
    """SOS for a decision's reason: three places, or as many more as keep it on its side of `target`, so that
    0.94986 reads "0.9499 below 0.95", never "0.950 below 0.95"."""
    for places in range(3, 12):
        text = f"{sos:.{places}f}"
        if (float(text) < target) == (sos < target):
            return text
    return repr(sos)
