"""The datagen pipeline end to end: `topseg bench datagen`.

Starts a local Dask cluster (`--workers`, default one per core), renders `--warmup` frames
per worker into a throwaway store (pybullet loads, numba compiles), then times `--frames`
frames into a fresh Zarr store exactly as `topseg datagen` writes them: `frames_per_s` is
first task submitted to last frame flagged complete. The workers' own clocks split that into
rendering and writing (compression + chunk files); `ideal_frames_per_s` is what the workers
would reach if the pipeline cost nothing beyond rendering, and `pipeline_overhead_pct` how
far below it the run fell. The `*_cpu_ms_per_frame` figures are the worker threads' CPU
time, which unlike wall time does not grow when other jobs share the cores. A second timed
run replays a few pre-rendered frames instead of rendering (`replay_frames_per_s`): that is
the ceiling the pipeline itself allows (compression, writing, scheduling, flags).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from topseg.core.errors import TopsegError
from topseg.core.formats.dataset import DatasetWriter, make_attrs
from topseg.core.synth.noise import parse_noise
from topseg.services.batch.datagen import dask_client, default_workers, generate
from topseg.services.batch.datagen.sources import generator_config, load_factory, resolve
from topseg.services.cli.options import int_range


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Frames, warm-up, workers, task size and generator of the run; temp stores in `--dir`."""
    parser.add_argument(
        "--frames", type=int_range(1, 10**7), default=240, help="frames in the timed run (240)"
    )
    parser.add_argument(
        "--warmup", type=int_range(0, 10**6), default=8, help="frames per worker before timing (8)"
    )
    parser.add_argument(
        "--workers", type=int_range(1, 1024), default=None, help="worker processes (one per core)"
    )
    parser.add_argument(
        "--chunk", type=int_range(1, 10**6), default=16, help="frames per Dask task (16)"
    )
    parser.add_argument("--mode", choices=("modeled", "non-modeled"), default="modeled")
    parser.add_argument("--noise", default="gaussian:15")
    parser.add_argument("--generator", default="synthesis", help="as for `topseg datagen`")
    parser.add_argument(
        "--dir", default=None, help="where the temporary stores go (default: $TMPDIR)"
    )


_REPLAY = "topseg.services.batch.bench.datagen:replay_source"
REPLAY_DISTINCT = 4


def replay_source(config: dict, seed: int):
    """Render REPLAY_DISTINCT frames once with the generator in `config`, then hand them out
    in turn: a frame source that costs nothing, to time the pipeline alone."""
    inner = load_factory(config["factory"])(config["config"], seed)
    frames = [inner(i) for i in range(REPLAY_DISTINCT)]
    if hasattr(inner, "close"):
        inner.close()
    return lambda index: frames[index % REPLAY_DISTINCT]


def _run(root: Path, name: str, generator: dict, frames: int, client, chunk: int) -> dict:
    attrs = make_attrs(
        seed=0,
        mode=generator["config"].get("mode", "modeled"),
        noise=generator["config"].get("noise", "none"),
        room=None,
        generator=generator,
        frames=frames,
    )
    with DatasetWriter.open(root / name, attrs) as writer:
        stats = generate(writer, client, chunk=chunk, progress=False, log_every=0)
    stats["bytes"] = sum(f.stat().st_size for f in (root / name).rglob("*") if f.is_file())
    return stats


def measure(args: argparse.Namespace) -> dict:
    """Warm up, then time a rendered run and a replayed run; the figures the module doc explains."""
    if args.frames < 1 or args.warmup < 0 or args.chunk < 1:
        raise TopsegError("--frames and --chunk must be >= 1, --warmup >= 0")
    target = resolve(args.generator)
    load_factory(target)
    noise = parse_noise(args.noise).spec
    generator = {"factory": target, "config": generator_config(target, args.mode, noise, None)}
    replay = {"factory": _REPLAY, "config": generator}
    workers = args.workers or default_workers()
    with tempfile.TemporaryDirectory(prefix="topseg-bench-datagen-", dir=args.dir) as tmp:
        root = Path(tmp)
        t0 = time.perf_counter()
        with dask_client(workers=workers) as client:
            startup_s = time.perf_counter() - t0
            warm = max(args.warmup * workers, 1)
            t0 = time.perf_counter()
            _run(root, "warmup", generator, warm, client, chunk=max(1, args.warmup))
            warmup_s = time.perf_counter() - t0
            main = _run(root, "timed", generator, args.frames, client, chunk=args.chunk)
            _run(root, "replay-warmup", replay, warm, client, chunk=max(1, args.warmup))
            rep = _run(root, "replay", replay, args.frames, client, chunk=args.chunk)
    n = main["frames"]
    render_ms = 1e3 * main["render_s"] / n
    write_ms = 1e3 * main["write_s"] / n
    ideal = main["workers"] * 1e3 / render_ms if render_ms > 0 else float("inf")
    raw_bytes = n * 480 * 640 * 3
    return {
        "generator": args.generator,
        "mode": args.mode,
        "noise": noise,
        "frames": n,
        "workers": main["workers"],
        "workers_used": main["workers_used"],
        "chunk": args.chunk,
        "startup_s": round(startup_s, 2),
        "warmup_s": round(warmup_s, 2),
        "frames_per_s": round(main["frames_per_s"], 1),
        "render_ms_per_frame": round(render_ms, 2),
        "write_ms_per_frame": round(write_ms, 2),
        "render_cpu_ms_per_frame": round(1e3 * main["render_cpu_s"] / n, 2),
        "write_cpu_ms_per_frame": round(1e3 * main["write_cpu_s"] / n, 2),
        "ideal_frames_per_s": round(ideal, 1),
        "pipeline_overhead_pct": round(100.0 * (1.0 - main["frames_per_s"] / ideal), 1),
        "replay_frames_per_s": round(rep["frames_per_s"], 1),
        "replay_write_ms_per_frame": round(1e3 * rep["write_s"] / rep["frames"], 2),
        "store_kb_per_frame": round(main["bytes"] / n / 1024, 1),
        "compression_ratio": round(raw_bytes / main["bytes"], 2),
    }
