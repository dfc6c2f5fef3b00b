"""The CUDA path on a GPU machine: gsplat against the numba CPU rasteriser on the benchmark scene of
bench/raster.py, then a full `station demo` timed, trained on CUDA by `TrainConfig.device` "auto".

    ./dev bench gpu                 # or: python bench/gpu.py [--skip-demo]

Where no NVIDIA GPU is present it says so and exits 0 before installing anything. Otherwise it builds
its own venv (.venv-gpu: a CUDA torch and gsplat, pinned below, beside this project) and reruns itself
there. gsplat compiles its CUDA kernels on first use, which needs the CUDA toolkit (nvcc). Writes
bench/results/raster_gpu.json.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# torch as in pyproject.toml; from PyPI on Linux x86-64 this resolves to the CUDA build.
PINS = ("torch==2.13.*", "gsplat==1.5.3", "ninja==1.13.*")
SCENES = ((2_000, 128), (20_000, 256))
IMAGE_ATOL = 2e-3  # float32 on both sides, polynomial exp here against __expf there
GRAD_REL = 2e-2    # gradient max error relative to the largest gradient, per parameter


def gpu_listed() -> str | None:
    """The GPUs nvidia-smi lists, or None (no driver, no tool, or no device): costs no download."""
    tool = shutil.which("nvidia-smi")
    if tool is None:
        return None
    try:
        out = subprocess.run([tool, "-L"], capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired):
        return None
    gpus = [line for line in out.stdout.splitlines() if line.startswith("GPU ")]
    return "\n".join(gpus) if out.returncode == 0 and gpus else None


def ensure_venv(venv: Path) -> Path:
    """Create or refresh the GPU venv when the pins or pyproject.toml change; returns its python."""
    stamp_of = hashlib.sha256(("\n".join(PINS) + (ROOT / "pyproject.toml").read_text()).encode()).hexdigest()[:16]
    python, stamp = venv / "bin" / "python", venv / f".installed-{stamp_of}"
    if stamp.exists():
        return python
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    pip = [str(python), "-m", "pip", "install", "--quiet"]
    subprocess.run(pip + ["--upgrade", "pip", "setuptools", "wheel"], check=True)
    subprocess.run(pip + [PINS[0], PINS[2]], check=True)
    # gsplat's setup.py imports torch, so no build isolation; BUILD_NO_CUDA defers its CUDA build to first use.
    subprocess.run(pip + ["--no-build-isolation", PINS[1]], check=True, env={**os.environ, "BUILD_NO_CUDA": "1"})
    subprocess.run(pip + ["-e", str(ROOT)], check=True)
    for old in venv.glob(".installed-*"):
        old.unlink()
    stamp.touch()
    return python


def _step(scene: dict, backend: str, device: str):
    """One training step's render and gradients on `device` -> image, alpha, grads (on the CPU)."""
    import torch

    from bench.raster import _render

    params = [scene[k].to(device).clone().requires_grad_(True)
              for k in ("means", "log_scales", "quats", "opacity_logits", "sh")]
    moved = {**scene, "viewmats": scene["viewmats"].to(device), "Ks": scene["Ks"].to(device)}
    img, alpha, _ = _render(moved, params, backend)
    (img - scene["target"].to(device)).abs().mean().backward()
    if device == "cuda":
        torch.cuda.synchronize()
    return img.detach().cpu(), alpha.detach().cpu(), [p.grad.cpu() for p in params]


def compare(n: int, size: int) -> dict:
    """gsplat (CUDA) against the numba kernels (CPU) on one benchmark scene: errors and step times."""
    import torch

    from bench.raster import bench_scene

    scene = bench_scene(n, size, size)
    img, alpha, grads = _step(scene, "cpu", "cpu")
    g_img, g_alpha, g_grads = _step(scene, "gsplat", "cuda")
    names = ("means", "log_scales", "quats", "opacity_logits", "sh")
    grad_rel = {name: float((a - b).abs().max() / b.abs().max().clamp(min=1e-12))
                for name, a, b in zip(names, g_grads, grads)}
    times = {}
    for backend, device in (("cpu", "cpu"), ("gsplat", "cuda")):
        walls = []
        for _ in range(5):
            started = time.perf_counter()
            _step(scene, backend, device)
            walls.append(time.perf_counter() - started)
        times[backend] = 1e3 * sorted(walls)[2]
    row = {"gaussians": n, "width": size, "height": size,
           "image_max_abs": float((g_img - img).abs().max()), "alpha_max_abs": float((g_alpha - alpha).abs().max()),
           "grad_max_rel": grad_rel, "cpu_step_ms": round(times["cpu"], 2), "cuda_step_ms": round(times["gsplat"], 2),
           "torch": torch.__version__, "device": torch.cuda.get_device_name(0)}
    row["agrees"] = (row["image_max_abs"] <= IMAGE_ATOL and row["alpha_max_abs"] <= IMAGE_ATOL
                     and all(v <= GRAD_REL for v in grad_rel.values()))
    return row


def time_demo() -> dict:
    """A full `station demo` in this venv: seconds, exit code, and the device the trainer chose (its
    `TrainConfig.device` "auto" takes CUDA when torch sees a GPU) read back from the demo's train metrics."""
    with tempfile.TemporaryDirectory(prefix="station-gpu-demo-") as out:
        started = time.monotonic()
        run = subprocess.run([sys.executable, "-m", "station", "demo", "--out", out], cwd=ROOT,
                             capture_output=True, text=True)
        seconds = time.monotonic() - started
        devices = sorted({json.loads(p.read_text())["report"].get("device", "unknown")
                          for p in Path(out).rglob("train_metrics.json")})
    tail = (run.stdout + run.stderr).strip().splitlines()[-15:]
    return {"seconds": round(seconds, 1), "exit_code": run.returncode, "trained_on": devices, "output_tail": tail}


def inside(skip_demo: bool, out: Path) -> int:
    import torch

    if not torch.cuda.is_available():
        print(f"bench gpu: nvidia-smi lists a GPU but torch {torch.__version__} in this venv sees no CUDA device "
              "(driver too old for its CUDA build?): nothing compared.")
        return 0
    sys.path.insert(0, str(ROOT))
    rows = [compare(n, size) for n, size in SCENES]
    print(f"{'gaussians':>9} {'size':>9} {'img err':>9} {'alpha err':>9} {'worst grad':>10} {'cpu ms':>8} "
          f"{'cuda ms':>8} agrees")
    for r in rows:
        print(f"{r['gaussians']:>9} {r['width']:>4}x{r['height']:<4} {r['image_max_abs']:>9.2e} "
              f"{r['alpha_max_abs']:>9.2e} {max(r['grad_max_rel'].values()):>10.2e} {r['cpu_step_ms']:>8.1f} "
              f"{r['cuda_step_ms']:>8.1f} {r['agrees']}")
    demo = None if skip_demo else time_demo()
    if demo is not None:
        print(f"station demo: {demo['seconds']:.0f} s, exit code {demo['exit_code']}, trained on {demo['trained_on']}")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"comparisons": rows, "demo": demo, "pins": PINS,
                               "tolerances": {"image_atol": IMAGE_ATOL, "grad_rel": GRAD_REL}}, indent=2) + "\n")
    print(f"wrote {out}")
    demo_ok = demo is None or (demo["exit_code"] == 0 and bool(demo["trained_on"])
                               and all(d.startswith("cuda") for d in demo["trained_on"]))
    return 0 if all(r["agrees"] for r in rows) and demo_ok else 1


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--skip-demo", action="store_true", help="compare and time the rasterisers only")
    parser.add_argument("--venv", type=Path, default=ROOT / ".venv-gpu")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "raster_gpu.json")
    parser.add_argument("--inside", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.inside:
        return inside(args.skip_demo, args.out)
    gpus = gpu_listed()
    if gpus is None:
        print("bench gpu: no NVIDIA GPU here (nvidia-smi is missing or lists no device); nothing installed, "
              "nothing run.")
        return 0
    print(f"bench gpu: found\n{gpus}")
    if shutil.which("nvcc") is None and not os.environ.get("CUDA_HOME"):
        print("bench gpu: gsplat builds its CUDA kernels on first use and needs the CUDA toolkit (nvcc on PATH "
              "or CUDA_HOME); install it and rerun.", file=sys.stderr)
        return 1
    python = ensure_venv(args.venv)
    cmd = [str(python), str(Path(__file__).resolve()), "--inside", "--out", str(args.out)]
    return subprocess.run(cmd + (["--skip-demo"] if args.skip_demo else []), cwd=ROOT).returncode


if __name__ == "__main__":
    sys.exit(main())
