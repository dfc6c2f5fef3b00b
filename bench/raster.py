"""Benchmark of the CPU rasteriser: one full training step and forward-only render, on `bench_scene`
(N random Gaussians in a cube before the camera). Prints two tables and writes bench/results/raster.json.

    python bench/raster.py            # headline configs, sweeps at reduced range (~2-3 min)
    python bench/raster.py --full     # sweeps 10k..400k Gaussians and 128^2..1024^2
    python bench/raster.py --against REV   # step time of this tree against revision REV, in one process

A step = projection + SH + binning + forward + L1 loss + backward to every parameter (no optimiser).
A step runs torch's ops on one thread, as the trainer does. Times are medians of wall-clock; CPU time (both
threads) is reported beside them because a shared machine inflates wall time, and the step's fastest wall
time too: a busy host only ever slows a step, here by up to 1.5x for seconds at a time. The breakdown times
each phase's kernels alone (forward and backward together), the trainer's Adam step beside them, and fits
every phase's CPU time over the Gaussian-count sweep as fixed ms + us per Gaussian, so each part of the
step's cost has an owner.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch/numba load their OpenMP runtimes

import argparse  # noqa: E402
import importlib  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import resource  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402

import numba  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from station.ngs import _kernels, _project_kernels  # noqa: E402
from station.ngs.conventions import rgb_to_sh  # noqa: E402
from station.ngs.raster import _validate, rasterization, set_num_threads, torch_threads  # noqa: E402
from station.ngs.raster_reference import camera_centres  # noqa: E402
from station.ngs.trainer import STEP_TORCH_THREADS  # noqa: E402

from machine import describe  # noqa: E402
from revisions import unpack_as, working_tree  # noqa: E402

REFERENCE_LIMIT = 2_000 * 128 * 128  # Gaussians x pixels beyond which the dense reference is skipped


def bench_scene(n: int, width: int, height: int, sh_degree: int = 3, seed: int = 0) -> dict:
    """The shared benchmark scene: N Gaussians in [-1,1]^3, camera 4 units away, fx = fy = 1.5 W."""
    g = torch.Generator().manual_seed(seed)
    spacing = (8.0 / n) ** (1.0 / 3.0)
    quats = torch.randn(n, 4, generator=g)
    sh = 0.1 * torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g)
    sh[:, 0] = rgb_to_sh(torch.rand(n, 3, generator=g))
    viewmat = torch.eye(4)
    viewmat[2, 3] = 4.0
    return {
        "means": torch.rand(n, 3, generator=g) * 2 - 1,
        "log_scales": math.log(0.5 * spacing) + 0.3 * torch.randn(n, 3, generator=g),
        "quats": quats / quats.norm(dim=-1, keepdim=True),
        "opacity_logits": torch.randn(n, generator=g),
        "sh": sh,
        "viewmats": viewmat[None],
        "Ks": torch.tensor([[1.5 * width, 0, width / 2], [0, 1.5 * width, height / 2], [0, 0, 1.0]])[None],
        "target": torch.rand(1, height, width, 3, generator=g),
        "width": width, "height": height, "sh_degree": sh_degree,
    }


def _render(scene: dict, params: list[torch.Tensor], backend: str, rasterize=rasterization):
    """The scene through `rasterize`: this tree's `rasterization`, or an older tree's under `--against`."""
    means, log_scales, quats, logits, sh = params
    return rasterize(means, quats, log_scales.exp(), torch.sigmoid(logits), sh, scene["viewmats"], scene["Ks"],
                     scene["width"], scene["height"], sh_degree=scene["sh_degree"], backend=backend)


def _step(scene: dict, params: list[torch.Tensor], backend: str = "cpu", rasterize=rasterization) -> None:
    """One step without the optimiser: render, L1 loss against the scene's target, backward to every parameter."""
    for p in params:
        p.grad = None
    img, _, _ = _render(scene, params, backend, rasterize)
    (img - scene["target"]).abs().mean().backward()


def step_walls(gaussians: int, size: int, repeats: int) -> tuple[list[float], float]:
    """Wall seconds of each of `repeats` steps on the bench scene (SH3, size²) after three warm-ups, and their CPU
    seconds together: what the thread and spin benches time, each in a process whose pools they set up first."""
    scene = bench_scene(gaussians, size, size)
    params = [scene[k].clone().requires_grad_(True) for k in ("means", "log_scales", "quats", "opacity_logits", "sh")]
    for _ in range(3):
        _step(scene, params)
    walls, cpu = [], time.process_time()
    for _ in range(repeats):
        started = time.perf_counter()
        _step(scene, params)
        walls.append(time.perf_counter() - started)
    return walls, time.process_time() - cpu


def _timed(fn, repeats: int) -> tuple[float, float]:
    """Median wall and CPU milliseconds of fn() after one warm-up call."""
    walls, cpus = _samples(fn, repeats)
    return statistics.median(walls), statistics.median(cpus)


def _samples(fn, repeats: int) -> tuple[list[float], list[float]]:
    """Sorted wall and CPU milliseconds of `repeats` calls of fn() after one warm-up call."""
    fn()
    walls, cpus = [], []
    for _ in range(repeats):
        w, c = time.perf_counter(), time.process_time()
        fn()
        walls.append(time.perf_counter() - w)
        cpus.append(time.process_time() - c)
    return sorted(1e3 * w for w in walls), sorted(1e3 * c for c in cpus)


def measure(n: int, width: int, height: int, sh_degree: int, threads: int, repeats: int) -> dict:
    scene = bench_scene(n, width, height, sh_degree)
    params = [scene[k].clone().requires_grad_(True) for k in ("means", "log_scales", "quats", "opacity_logits", "sh")]

    def forward() -> None:
        with torch.no_grad():
            _render(scene, params, "cpu")

    with torch_threads(STEP_TORCH_THREADS):  # as the trainer runs a step
        walls, cpus = _samples(lambda: _step(scene, params), repeats)
    step_ms, step_cpu_ms = statistics.median(walls), statistics.median(cpus)
    forward_ms, _ = _timed(forward, repeats)
    parts = breakdown(scene, params, (step_ms, step_cpu_ms), repeats)
    reference_ms = None
    if n * width * height <= REFERENCE_LIMIT:
        reference_ms, _ = _timed(lambda: _step(scene, params, "torch"), max(1, repeats // 3))
    return {"gaussians": n, "width": width, "height": height, "sh_degree": sh_degree, "threads": threads,
            "step_ms": round(step_ms, 2), "step_best_ms": round(walls[0], 2), "step_cpu_ms": round(step_cpu_ms, 2),
            "forward_ms": round(forward_ms, 2),
            "reference_step_ms": None if reference_ms is None else round(reference_ms, 2),
            "speedup_vs_reference": None if reference_ms is None else round(reference_ms / step_ms, 1),
            "intersections": parts.pop("intersections"), "breakdown": parts}


PHASES = ("checks", "projection", "sh", "binning_and_sort", "raster_forward", "raster_backward", "torch_glue",
          "optimizer")


def breakdown(scene: dict, params: list[torch.Tensor], step_times: tuple[float, float], repeats: int) -> dict:
    """Median wall and CPU ms of each phase of a step, run alone on the step's own inputs. torch_glue is the
    step's remainder (activations, autograd, loss, tensor<->array copies); optimizer is the trainer's
    per-parameter Adam, which is not part of `step_ms`."""
    w, h, deg = scene["width"], scene["height"], scene["sh_degree"]
    means, log_scales, quats, logits, sh = (p.detach() for p in params)
    scales, opac = log_scales.exp(), torch.sigmoid(logits)
    gauss = [t.contiguous().numpy() for t in (means, quats, scales)]
    coeffs = sh.contiguous().numpy()
    no_sh = coeffs[:, :1]
    cams = [t.contiguous().numpy() for t in (scene["viewmats"], scene["Ks"], camera_centres(scene["viewmats"]))]
    op = opac.numpy()
    rng = torch.Generator().manual_seed(1)

    def upstream(shape):
        return (0.01 * torch.randn(shape, generator=rng)).numpy()

    def projector(degree: int, k: np.ndarray) -> Callable[[], None]:
        """Projection forward and backward at `degree`, its upstream gradients drawn once, outside the timing."""
        shapes = _project_kernels.project_fwd(*gauss, k, degree, *cams, w, h, 0.01, 1e10)
        grads = [upstream(a.shape) for a in (shapes[0], shapes[1], shapes[2], shapes[4])]

        def project() -> None:
            out = _project_kernels.project_fwd(*gauss, k, degree, *cams, w, h, 0.01, 1e10)
            # want_pose False: a training step's poses are constants
            _project_kernels.project_bwd(*gauss, k, degree, *cams, w, h, out[3], out[4], *grads, False)
        return project

    m2, conics, depths, radii, colors = _project_kernels.project_fwd(*gauss, coeffs, deg, *cams, w, h, 0.01, 1e10)
    m2, conics, depths, radii, colors = m2[0], conics[0], depths[0], radii[0], colors[0]
    bins = _kernels.bin_gaussians(m2, conics, op, radii, depths, w, h)
    img, t_final, n_proc, taken = _kernels.rasterize_fwd(m2, conics, colors, op, bins[0], bins[1], bins[2], w, h,
                                                         True)
    g_img, g_alpha, bg = upstream(img.shape), np.zeros((h, w), np.float32), np.zeros(3, np.float32)

    def backward() -> None:
        slots = _kernels.rasterize_bwd(m2, conics, colors, op, bg, bins[0], bins[1], taken, w, h, img, t_final,
                                       n_proc, g_img, g_alpha, True)
        _kernels.reduce_per_gaussian(slots, bins[1], m2.shape[0])

    for p in params:
        p.grad = torch.zeros_like(p)
    optimizers = trainer_optimizers("station", params)

    def adam() -> None:
        for opt in optimizers:
            opt.step()

    timed = {
        "checks": _timed(lambda: _validate(means, quats, scales, opac, sh, scene["viewmats"], scene["Ks"], w, h, deg,
                                           None), repeats),
        "projection": _timed(projector(-1, no_sh), repeats),
        "projection_sh": _timed(projector(deg, coeffs), repeats),
        "binning_and_sort": _timed(lambda: _kernels.bin_gaussians(m2, conics, op, radii, depths, w, h), repeats),
        "raster_forward": _timed(lambda: _kernels.rasterize_fwd(m2, conics, colors, op, bins[0], bins[1], bins[2], w,
                                                                h, True), repeats),
        "raster_backward": _timed(backward, repeats),
        "optimizer": _timed(adam, repeats),
    }
    with_sh = timed.pop("projection_sh")
    timed["sh"] = (max(with_sh[0] - timed["projection"][0], 0.0), max(with_sh[1] - timed["projection"][1], 0.0))
    inside = [timed[k] for k in PHASES if k not in ("torch_glue", "optimizer")]
    timed["torch_glue"] = (max(step_times[0] - sum(t[0] for t in inside), 0.0),
                           max(step_times[1] - sum(t[1] for t in inside), 0.0))
    for p in params:
        p.grad = None
    return {k: {"wall_ms": round(timed[k][0], 2), "cpu_ms": round(timed[k][1], 2)} for k in PHASES} | {
        "intersections": int(bins[1].shape[0])}


def fit_per_gaussian(rows: list[dict]) -> dict:
    """Least-squares CPU ms = fixed + per-Gaussian slope, per phase, over rows at one image size."""
    n = np.array([r["gaussians"] for r in rows], float)
    out = {}
    for phase in PHASES + ("step",):
        y = np.array([r["step_cpu_ms"] if phase == "step" else r["breakdown"][phase]["cpu_ms"] for r in rows])
        slope, fixed = np.polyfit(n, y, 1)
        out[phase] = {"fixed_cpu_ms": round(float(fixed), 2), "cpu_us_per_gaussian": round(1e3 * float(slope), 4)}
    return out


def cold_start_ms() -> float:
    """Wall time of a fresh interpreter importing the rasteriser and rendering once (warm numba cache)."""
    code = ("import time; t = time.perf_counter(); import sys; sys.path.insert(0, 'BENCH');"
            "from raster import bench_scene, _render; s = bench_scene(1000, 64, 64);"
            "p = [s[k] for k in ('means', 'log_scales', 'quats', 'opacity_logits', 'sh')];"
            "_render(s, p, 'cpu'); print((time.perf_counter() - t) * 1e3)").replace("BENCH", str(Path(__file__).parent))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return round(float(out.stdout.strip().splitlines()[-1]), 1)


def step_peak_rss_mb(n: int, width: int, height: int) -> float:
    """Peak resident memory of a fresh process that builds the scene and runs two full training steps."""
    code = ("import os; os.environ.setdefault('OMP_WAIT_POLICY', 'PASSIVE'); import sys, torch;"
            "sys.path.insert(0, 'BENCH'); from raster import bench_scene, _render;"
            f"s = bench_scene({n}, {width}, {height});"
            "p = [s[k].clone().requires_grad_(True) for k in ('means', 'log_scales', 'quats', 'opacity_logits', 'sh')];"
            "[(_render(s, p, 'cpu')[0] - s['target']).abs().mean().backward() for _ in range(2)];"
            # VmHWM, not ru_maxrss: Linux carries ru_maxrss over exec from the forking parent (this bench)
            "print(next(int(l.split()[1]) for l in open('/proc/self/status') if l.startswith('VmHWM')) / 1024)"
            ).replace("BENCH", str(Path(__file__).parent))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return round(float(out.stdout.strip().splitlines()[-1]), 1)


AB_CONFIGS = ((20_000, 256, 15), (100_000, 512, 5))


def trainer_optimizers(package: str, params: list[torch.Tensor]) -> list[torch.optim.Optimizer]:
    """The Adam optimisers that `package`'s trainer builds, over the bench's parameters."""
    from types import SimpleNamespace

    trainer = importlib.import_module(f"{package}.ngs.trainer")
    named = dict(zip(("means", "scales", "quats", "opacities", "sh0"), params))
    host = SimpleNamespace(cfg=trainer.TrainConfig(), scene=SimpleNamespace(scene_scale=1.0),
                           model=SimpleNamespace(params=named))
    return list(trainer.Trainer._make_optimizers(host).values())


class _TreeStep:
    """One tree's training step on the shared scene: render, L1 loss, backward, and (train) its own Adam."""

    def __init__(self, package: str, scene: dict):
        self.rasterization = importlib.import_module(f"{package}.ngs.raster").rasterization
        self.scene = scene
        self.params = [scene[k].clone().requires_grad_(True)
                       for k in ("means", "log_scales", "quats", "opacity_logits", "sh")]
        self.optimizers = trainer_optimizers(package, self.params)

    def step(self) -> None:
        with torch_threads(STEP_TORCH_THREADS):  # as the trainer runs a step
            _step(self.scene, self.params, "cpu", self.rasterization)

    def train_step(self) -> None:
        self.step()
        with torch_threads(STEP_TORCH_THREADS):
            for opt in self.optimizers:
                opt.step()


def against(rev: str, rounds: int, out: Path) -> None:
    """This tree's step against revision `rev`'s, both imported into this one process (rev's package renamed) and
    run in turns of a few steps each, so both see the same machine: on a shared host, the same kernels timed in
    processes minutes apart differ by more than most changes under test. Quotes per-config medians and their
    ratio; each tree's warm-up (numba compile) is not counted."""
    with tempfile.TemporaryDirectory(prefix="raster-ab-") as old:
        before = unpack_as(rev, Path(old), "station_before")
        sys.path.insert(0, old)
        packages = {"before": "station_before", "after": "station"}
        rows = []
        keys = ("step_ms", "step_cpu_ms", "train_step_ms", "train_step_cpu_ms")
        print("medians, ms; 'train' adds each tree's own Adam step; ratios are after / before")
        print(f"{'gaussians':>9} {'size':>9} {'step wall':>15} {'ratio':>6} {'step cpu':>15} {'ratio':>6} "
              f"{'train wall':>15} {'ratio':>6} {'train cpu':>15} {'ratio':>6} {'load':>5}")
        for n, size, repeats in AB_CONFIGS:
            scene = bench_scene(n, size, size)
            trees = {name: _TreeStep(package, scene) for name, package in packages.items()}
            for tree in trees.values():
                tree.train_step()
            runs = {name: [] for name in trees}
            for _ in range(rounds):
                for name, tree in trees.items():
                    step_ms, step_cpu_ms = _timed(tree.step, repeats)
                    train_ms, train_cpu_ms = _timed(tree.train_step, repeats)
                    runs[name].append({"step_ms": round(step_ms, 2), "step_cpu_ms": round(step_cpu_ms, 2),
                                       "train_step_ms": round(train_ms, 2), "train_step_cpu_ms": round(train_cpu_ms, 2),
                                       "load_1min": round(os.getloadavg()[0], 2)})
            med = {(name, key): float(np.median([r[key] for r in runs[name]])) for name in trees for key in keys}
            ratio = {key: round(med["after", key] / med["before", key], 3) for key in keys}
            load = float(np.median([r["load_1min"] for name in trees for r in runs[name]]))
            row = {"gaussians": n, "width": size, "height": size, "runs": runs,
                   "median": {f"{name}_{key}": round(v, 2) for (name, key), v in med.items()},
                   "cpu_ratio_after_over_before": ratio["step_cpu_ms"],
                   "wall_ratio_after_over_before": ratio["step_ms"],
                   "train_cpu_ratio_after_over_before": ratio["train_step_cpu_ms"],
                   "train_wall_ratio_after_over_before": ratio["train_step_ms"], "median_load_1min": load}
            rows.append(row)
            print(f"{n:>9} {size:>4}x{size:<4} " + " ".join(
                f"{med['before', key]:>7.1f}>{med['after', key]:<7.1f} {ratio[key]:>6.2f}" for key in keys)
                + f" {load:>5.1f}", flush=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"benchmark": "raster", "before": before, "after": working_tree(),
                               "rounds": rounds, "threads": 2, "method": "one process, trees in turns",
                               "machine": describe(),
                               "configs": rows}, indent=2) + "\n")
    print(f"wrote {out}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--full", action="store_true", help="full sweeps (10k..400k, 128^2..1024^2)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--out", type=Path, default=None, help="default bench/results/raster.json "
                        "(raster_ab.json with --against)")
    parser.add_argument("--against", metavar="REV", help="time this tree's step against git revision REV")
    parser.add_argument("--rounds", type=int, default=12, help="with --against: turns of each tree per config")
    args = parser.parse_args()
    results = Path(__file__).parent / "results"
    set_num_threads(args.threads)
    if args.against:
        return against(args.against, args.rounds, args.out or results / "raster_ab.json")
    args.out = args.out or results / "raster.json"
    headline = [(20_000, 256, 256, 3), (100_000, 512, 512, 3), (2_000, 128, 128, 3)]
    counts = [10_000, 20_000, 50_000, 100_000, 200_000, 400_000] if args.full else [10_000, 50_000]
    sizes = [128, 256, 512, 1024] if args.full else [128, 512]
    sweep = [(n, 256, 256, 3) for n in counts] + [(20_000, s, s, 3) for s in sizes]
    configs, seen = [], set()
    print(f"{'gaussians':>9} {'size':>9} {'sh':>2} {'thr':>3} {'step ms':>8} {'best ms':>8} {'cpu ms':>8} "
          f"{'fwd ms':>7} {'ref ms':>8} {'x ref':>6}")
    for n, w, h, d in headline + sweep:
        if (n, w, h, d) in seen:
            continue
        seen.add((n, w, h, d))
        row = measure(n, w, h, d, args.threads, args.repeats if n * w * h <= 100_000 * 512 * 512 else 2)
        row["role"] = "headline" if (n, w, h, d) in headline else "sweep"
        configs.append(row)
        ref_ms = "-" if row["reference_step_ms"] is None else f"{row['reference_step_ms']:.0f}"
        ratio = "-" if row["speedup_vs_reference"] is None else f"{row['speedup_vs_reference']:.0f}"
        print(f"{n:>9} {w:>4}x{h:<4} {d:>2} {args.threads:>3} {row['step_ms']:>8.1f} {row['step_best_ms']:>8.1f} "
              f"{row['step_cpu_ms']:>8.1f} {row['forward_ms']:>7.1f} {ref_ms:>8} {ratio:>6}", flush=True)
    short = {"checks": "chk", "projection": "proj", "sh": "sh", "binning_and_sort": "bin", "raster_forward": "fwd",
             "raster_backward": "bwd", "torch_glue": "glue", "optimizer": "adam"}
    print("\nCPU ms per phase (both threads; 'adam' is the optimiser step, outside 'step ms'):")
    print(f"{'gaussians':>9} {'size':>9} " + " ".join(f"{short[k]:>6}" for k in PHASES) + f" {'isects':>8}")
    for row in configs:
        print(f"{row['gaussians']:>9} {row['width']:>4}x{row['height']:<4} "
              + " ".join(f"{row['breakdown'][k]['cpu_ms']:>6.1f}" for k in PHASES) + f" {row['intersections']:>8}")
    fit = fit_per_gaussian([r for r in configs if (r["width"], r["height"], r["sh_degree"]) == (256, 256, 3)])
    print("\nfit over the 256x256 count sweep, CPU: fixed ms + us per Gaussian")
    for phase, f in fit.items():
        print(f"{phase:>16} {f['fixed_cpu_ms']:>8.2f} ms {f['cpu_us_per_gaussian']:>8.3f} us")
    cold = cold_start_ms()
    print(f"cold start (fresh process, warm numba cache, import + first 1k render): {cold:.0f} ms")
    peak = step_peak_rss_mb(100_000, 512, 512)
    print(f"peak memory of a process training at 100k / 512x512 (import included): {peak:.0f} MB")
    result = {
        "machine": {**describe(), "load_average": os.getloadavg()},
        "threads": args.threads, "torch": torch.__version__, "numba": numba.__version__,
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),  # this whole bench
        "peak_rss_100k_512_mb": peak,
        "cold_start_ms": cold, "configs": configs, "fit_256x256_cpu": fit,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
