"""The paper's training configuration through `topseg train`: `topseg bench train`.

Runs `topseg train` as a user does (a child process, local Dask cluster, a progress bar per
tree) with the paper's full configuration (T=5, D=19, PC=300, R=K=100, linear splits, 2000
pixels per frame) and F = `--scale` x 1600 frames per tree. Without `--data` it first renders a
modeled dataset with the realistic Kinect noise just large enough for F training frames
(cached under `out/bench-train/`, not counted in the training figures).

Figures: `seconds` (wall, process start to model written: Dask start-up, reading frames,
training, validation and writing included), `cpu_seconds` (user + system of the whole process
tree) and `peak_rss_mb`, the largest sum of resident memory over the process tree (train and
its Dask worker processes), sampled every `--sample-s` seconds by a thread; `per_process_peak_mb`
is each process's own maximum. Summed RSS counts shared library pages once per process, so it
is an upper bound of the memory the run needs.
"""

from __future__ import annotations

import argparse
import math
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import psutil

from topseg.core.errors import TopsegError
from topseg.core.forest.model_file import load_model
from topseg.core.formats.dataset import open_dataset
from topseg.services.cli.options import finite, int_range, non_negative_int

PAPER = {
    "trees": 5,
    "depth": 19,
    "frames_per_tree": 1600,
    "features": 300,
    "responses": 100,
    "thresholds": 100,
    "split": "linear",
}
TARGET_SECONDS = 15 * 60
TARGET_RSS_MB = 8 * 1024
VALIDATION = 0.1


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """`topseg bench train`'s options."""
    parser.add_argument(
        "--scale",
        type=finite(1e-4, 100),
        default=0.05,
        help="fraction of the paper's F = 1600 frames per tree (1 = the paper; default 0.05)",
    )
    parser.add_argument(
        "--data", type=Path, default=None, help="dataset to train on (default: generate one)"
    )
    parser.add_argument(
        "--keep-model", type=Path, default=None, help="keep the trained model at this path"
    )
    parser.add_argument(
        "--workers", type=int_range(1, 1024), default=None, help="as for `topseg train`"
    )
    parser.add_argument(
        "--seed", type=non_negative_int, default=0, help="training (and dataset) seed"
    )
    parser.add_argument(
        "--cache", type=Path, default=Path("out/bench-train"), help="where generated data goes"
    )
    parser.add_argument(
        "--sample-s", type=finite(0.01, 60), default=0.2, help="memory sampling period"
    )


def frames_per_tree(scale: float) -> int:
    """F at this scale: the paper's 1600 x scale, at least 1."""
    return max(1, round(PAPER["frames_per_tree"] * scale))


class TreeSampler:
    """Sample the resident memory and CPU time of a process and all its descendants."""

    def __init__(self, pid: int, period: float):
        self.root = psutil.Process(pid)
        self.period = period
        self.peak_total = 0  # bytes
        self.peak = {}  # pid -> (name, bytes)
        self.cpu = {}  # pid -> last seen user + system seconds (of itself)
        self.max_processes = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    def __enter__(self) -> TreeSampler:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()

    def sample(self) -> None:
        """One sample: every process of the tree's RSS and CPU time; updates the peaks."""
        try:
            procs = [self.root, *self.root.children(recursive=True)]
        except psutil.Error:
            return
        total = 0
        for p in procs:
            try:
                with p.oneshot():
                    rss = p.memory_info().rss
                    t = p.cpu_times()
                    name = _describe(p)
            except psutil.Error:
                continue
            total += rss
            self.cpu[p.pid] = t.user + t.system
            if rss > self.peak.get(p.pid, ("", 0))[1]:
                self.peak[p.pid] = (name, rss)
        self.peak_total = max(self.peak_total, total)
        self.max_processes = max(self.max_processes, len(procs))

    def _loop(self) -> None:
        while not self._stop.is_set():
            self.sample()
            self._stop.wait(self.period)


def _describe(p) -> str:
    """A short name for a process of the tree: train, dask worker, resource tracker..."""
    cmd = " ".join(p.cmdline())
    if "topseg.services.cli" in cmd and " train " in f"{cmd} ":
        return "topseg train"
    if "spawn_main" in cmd or "multiprocessing" in cmd:
        return "dask worker" if "--multiprocessing-fork" in cmd else "multiprocessing helper"
    return p.name()


def ensure_dataset(frames: int, seed: int, cache: Path) -> Path:
    """A modeled Kinect-noise dataset of `frames` frames under `cache`, generated once."""
    path = cache / f"modeled-kinect-{frames}-seed{seed}.zarr"
    if path.exists():
        try:
            if len(open_dataset(path)) == frames:
                return path
        except TopsegError:
            pass  # incomplete or damaged: datagen resumes or says why
    cache.mkdir(parents=True, exist_ok=True)
    cmd = [
        sys.executable,
        "-m",
        "topseg.services.cli",
        "datagen",
        "--mode",
        "modeled",
        "--noise",
        "kinect",
        "--frames",
        str(frames),
        "--seed",
        str(seed),
        "--out",
        str(path),
        "--no-progress",
    ]
    print(f"generating {frames} modeled frames into {path} (not timed)", file=sys.stderr)
    done = subprocess.run(cmd, stdout=sys.stderr, stderr=sys.stderr)
    if done.returncode != 0:
        raise TopsegError(f"generating the dataset failed (exit {done.returncode})")
    return path


def train_command(data: Path, out: Path, f: int, seed: int, workers: int | None) -> list[str]:
    """The `topseg train` command line of the paper's configuration at F = `f` frames per tree."""
    cmd = [sys.executable, "-m", "topseg.services.cli", "train", "--data", str(data)]
    cmd += ["--out", str(out), "--seed", str(seed), "--validation", str(VALIDATION)]
    cmd += ["--trees", str(PAPER["trees"]), "--depth", str(PAPER["depth"])]
    cmd += ["--features", str(PAPER["features"]), "--responses", str(PAPER["responses"])]
    cmd += ["--thresholds", str(PAPER["thresholds"]), "--split", PAPER["split"]]
    cmd += ["--frames-per-tree", str(f)]
    if workers:
        cmd += ["--workers", str(workers)]
    return cmd


def measure(args: argparse.Namespace) -> dict:
    """Run `topseg train` once as a child process and return its figures (see the module doc)."""
    if not args.scale > 0:
        raise TopsegError(f"--scale must be > 0, got {args.scale}")
    f = frames_per_tree(args.scale)
    if args.data is None:
        data = ensure_dataset(math.ceil(f / (1 - VALIDATION)) + 1, args.seed, args.cache)
    else:
        data = args.data
    with tempfile.TemporaryDirectory(prefix="topseg-bench-train-") as tmp:
        out = Path(tmp) / "model.npz"
        cmd = train_command(data, out, f, args.seed, args.workers)
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=sys.stderr, stderr=sys.stderr)
        with TreeSampler(proc.pid, args.sample_s) as sampler:
            rc = proc.wait()
        seconds = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        if rc != 0:
            raise TopsegError(f"`topseg train` failed (exit {rc}): {' '.join(cmd)}")
        forest, header = load_model(out)
        model_mb = out.stat().st_size / 2**20
        if args.keep_model:
            args.keep_model.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(out, args.keep_model)
    waited_cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    cpu = max(waited_cpu, sum(sampler.cpu.values()))
    peak_mb = sampler.peak_total / 2**20
    val = (header.get("validation") or {}).get("scores") or {}
    recipe = header["recipe"]["config"]
    return {
        "scale": args.scale,
        "config": {k: v for k, v in PAPER.items() if k != "frames_per_tree"}
        | {"frames_per_tree": f, "pixels_per_frame": recipe["pixels_per_frame"]},
        "data": str(data),
        "dataset_frames": header["dataset"]["frames"],
        "n_samples_per_tree": f * recipe["pixels_per_frame"],
        "n_samples": PAPER["trees"] * f * recipe["pixels_per_frame"],
        "seconds": round(seconds, 1),
        "train_seconds": header.get("train_seconds"),
        "cpu_seconds": round(cpu, 1),
        "cores": os.cpu_count(),
        "load_average_1m": round(os.getloadavg()[0], 2),
        "peak_rss_mb": round(peak_mb, 1),
        "per_process_peak_mb": sorted(
            (round(b / 2**20, 1) for _, b in sampler.peak.values()), reverse=True
        ),
        "processes": sampler.max_processes,
        "nodes": forest.n_nodes,
        "depth": forest.depth,
        "model_mb": round(model_mb, 1),
        "validation_avg_f1": val.get("avg_f1"),
        "target_seconds": TARGET_SECONDS,
        "target_peak_rss_mb": TARGET_RSS_MB,
        # the targets are for the paper's configuration only
        "met": (seconds <= TARGET_SECONDS and peak_mb <= TARGET_RSS_MB)
        if args.scale == 1
        else None,
    }
