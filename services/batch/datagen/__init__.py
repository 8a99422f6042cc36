"""Render a synthetic dataset into a Zarr store on Dask: scenes drawn from the density
function, ray cast from a camera mount and sensor drawn for each frame (`--mounts random`) or
from the paper's Kinect v1 3.5 m up (`--mounts paper`), with the sensor's noise and exact
labels. Frame i depends only on (--seed, i), so a rerun resumes where it stopped.
`topseg datagen preview PATH` draws a contact sheet to check the scenes by eye.

    topseg datagen --mode modeled --frames 2000 --out data/modeled.zarr --seed 1
    topseg datagen --mounts paper --noise gaussian:15 --frames 2000 --out data/paper.zarr
    topseg datagen preview data/modeled.zarr

Mounts: by default every frame draws its own camera mount (`--mounts random`: height
U[2.4, 4.5] m, pitch and roll U[-10, 10] deg, a sensor from `--sensors`, all four by default,
with its resolution and, with `--noise sensor` (the default then), its own noise family), and
people walk in and out of view; `--mounts paper` renders every frame from the paper's Kinect v1
3.5 m straight down (noise gaussian:15 by default), as the paper's experiments do.

The store's folder is created (with its parents) when missing. Frames are rendered on a
local Dask cluster (`topseg.services.batch.dask_cluster`: one single-threaded worker process per
core; pybullet is not thread-safe) or on an existing scheduler (`--scheduler
tcp://host:port`, whose workers must see `--out` at the same path). Work goes out in tasks of `--chunk` consecutive
frames; a task renders its frames and writes them straight into the store, returning only
their indices and timings, and this process then sets their `complete` flags. Frame i is
rendered from a seed that is a pure function of (--seed, i), so the dataset is the same
whatever the number of workers. Rerunning the same command after an interruption (Ctrl-C,
SIGTERM, SIGKILL, a full disk) resumes it: frames without their flag are rendered again.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from topseg.core.errors import TopsegError
from topseg.core.formats.dataset import DatasetWriter, FrameWriter, dataset_os_error, make_attrs
from topseg.core.synth.noise import parse_noise
from topseg.core.synth.rooms import ROOMS
from topseg.core.synth.synthesis import MountDistribution
from topseg.services.batch.dask_cluster import dask_client, default_workers
from topseg.services.cli import describe
from topseg.services.cli.options import int_range, non_negative_int

__all__ = ["add_arguments", "dask_client", "default_workers", "generate", "render_chunk", "run"]

log = logging.getLogger("topseg.datagen")

MODES = ("modeled", "non-modeled", "cell")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """`topseg datagen`'s options and its `preview` subcommand."""
    parser.add_argument(
        "--mode",
        choices=MODES,
        default="modeled",
        help="scene model: the paper's modeled or non-modeled scenes, or cell (robot cells: "
        "robots, cell objects, people working at them, and a share of the paper's scenes) "
        "(default: modeled)",
    )
    parser.add_argument(
        "--robot-urdf",
        action="append",
        default=[],
        metavar="FILE",
        help="with --mode cell: your own robot's URDF (its meshes beside it or under "
        "package:// paths it resolves), drawn for half of the robots; repeatable",
    )
    parser.add_argument(
        "--robots",
        default=None,
        metavar="NAMES",
        help="with --mode cell: comma-separated catalogue robots to draw from (random for "
        "random arms among them), or none to draw only --robot-urdf robots (default: the whole "
        "catalogue and random arms)",
    )
    parser.add_argument(
        "--frames", type=int_range(1, 10**8), help="number of frames in the dataset"
    )
    parser.add_argument(
        "--out",
        help="dataset directory (a Zarr v3 store) to create or resume; missing folders above "
        "it are created",
    )
    parser.add_argument("--seed", type=non_negative_int, default=0, help="dataset seed (default 0)")
    parser.add_argument(
        "--noise",
        default=None,
        help="sensor (each frame's sensor's own noise) | none | gaussian:<sigma_mm> | kinect | "
        "tof | stereo (default: sensor with random mounts, gaussian:15 with the paper's)",
    )
    parser.add_argument(
        "--mounts",
        choices=("random", "paper"),
        default=None,
        help="random: a camera mount drawn per frame (default for the synthesis generator); "
        "paper: the paper's fixed Kinect v1 mount (default for other generators)",
    )
    parser.add_argument(
        "--sensors",
        default=None,
        help="comma-separated sensors random mounts draw from, each as often as the others "
        "or NAME:N for N times as often (default: all of kinect_v1,kinect_v2,oak_d,"
        "realsense_d435; the bundled model's recipe weights the stereo cameras, "
        "scripts/make_model.sh)",
    )
    parser.add_argument(
        "--room", default=None, help=f"{' | '.join(ROOMS)} (default: a random one per frame)"
    )
    parser.add_argument(
        "--generator",
        default="synthesis",
        help="synthesis (the paper's scenes, default), procedural, or module:function",
    )
    parser.add_argument(
        "--scheduler", help="address of a running Dask scheduler (default: local cluster)"
    )
    parser.add_argument(
        "--workers", type=int_range(1, 1024), help="local worker processes (default: one per core)"
    )
    parser.add_argument(
        "--chunk", type=int_range(1, 10**6), default=16, help="frames per Dask task (default 16)"
    )
    parser.add_argument(
        "--progress",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="progress bar (default: on when stderr is a terminal)",
    )
    sub = parser.add_subparsers(dest="datagen_command", metavar="{preview,cell-sequence}")
    from topseg.services.batch.datagen import cell_sequence
    from topseg.services.batch.datagen import preview as datagen_preview

    p = sub.add_parser(
        "preview",
        help=datagen_preview.HELP,
        description=describe.description(datagen_preview.__doc__, "docs/howto/retrain.md"),
        formatter_class=describe.ParagraphFormatter,
    )
    datagen_preview.add_arguments(p)
    p = sub.add_parser(
        "cell-sequence",
        help=cell_sequence.HELP,
        description=describe.description(cell_sequence.__doc__, "docs/howto/retrain.md"),
        formatter_class=describe.ParagraphFormatter,
    )
    cell_sequence.add_arguments(p)


def cell_config(args: argparse.Namespace) -> dict | None:
    """The cell settings `--robot-urdf` and `--robots` ask for (None: the defaults); every
    URDF is loaded here, so a bad file fails before a store or a cluster exists."""
    if args.mode != "cell":
        if args.robot_urdf or args.robots is not None:
            raise TopsegError("--robot-urdf and --robots need --mode cell")
        return None
    from topseg.core.synth import robots

    urdfs = [str(Path(f).resolve()) for f in args.robot_urdf]
    for f in urdfs:
        robots.robot_model(f)
    names: list[str] = []
    if args.robots is not None:
        names = (
            []
            if args.robots.strip() == "none"
            else [n.strip() for n in args.robots.split(",") if n.strip()]
        )
        known = (*robots.ROBOTS, robots.RANDOM)
        unknown = [n for n in names if n not in known]
        if unknown:
            raise TopsegError(f"--robots: unknown {unknown}; known: {', '.join(known)}")
        if not names and not urdfs:
            raise TopsegError("--robots none needs at least one --robot-urdf")
    cell: dict = {"robot_urdfs": urdfs, "robot_names": names}
    if args.robots is not None and not names:
        cell["user_robot_share"] = 1.0
    return cell


# ---------------------------------------------------------------- worker side

_CACHE: dict[str, tuple[str, Any]] = {}


def _cached(slot: str, key: str, make):
    """One live object per slot per worker process (a new key closes the old object)."""
    held = _CACHE.get(slot)
    if held is not None and held[0] == key:
        return held[1]
    if held is not None and hasattr(held[1], "close"):
        held[1].close()
    _CACHE.pop(slot, None)
    obj = make()
    _CACHE[slot] = (key, obj)
    return obj


def render_chunk(path: str, store_key: str, generator: dict, seed: int, indices: list[int]) -> dict:
    """Dask task: render frames `indices` and write them into the store at `path`.

    The frame source (e.g. a Synthesizer with its pybullet client) and the store's writer stay
    cached in the worker process between tasks.
    """
    from topseg.services.batch.datagen.sources import load_factory

    source_key = json.dumps([generator, seed], sort_keys=True)
    source = _cached(
        "source", source_key, lambda: load_factory(generator["factory"])(generator["config"], seed)
    )
    writer = _cached("writer", store_key, lambda: FrameWriter(path))
    # wall and CPU seconds (CPU of this thread: what the work costs, whatever else runs)
    clock = {"render_s": 0.0, "write_s": 0.0, "render_cpu_s": 0.0, "write_cpu_s": 0.0}
    for i in indices:
        t0, c0 = time.perf_counter(), time.thread_time()
        depth, labels, scene = source(int(i))
        t1, c1 = time.perf_counter(), time.thread_time()
        writer.write(int(i), depth, labels, scene)
        clock["render_s"] += t1 - t0
        clock["render_cpu_s"] += c1 - c0
        clock["write_s"] += time.perf_counter() - t1
        clock["write_cpu_s"] += time.thread_time() - c1
    return {"indices": list(indices), **clock, "pid": os.getpid()}


# ---------------------------------------------------------------- client side


def _chunks(todo: np.ndarray, size: int) -> list[list[int]]:
    return [todo[i : i + size].tolist() for i in range(0, len(todo), size)]


def _progress_bar(total: int, enabled: bool | None):
    from tqdm import tqdm

    if enabled is None:
        enabled = sys.stderr.isatty()
    return tqdm(total=total, unit="frame", disable=not enabled, file=sys.stderr, dynamic_ncols=True)


def generate(
    writer,
    client,
    *,
    chunk: int = 16,
    progress: bool | None = None,
    log_every: float = 0.1,
) -> dict:
    """Render every frame `writer` still lacks on `client`; set flags as tasks finish.

    The workers get the generator and seed as stored in the dataset's attributes, so what
    is recorded is exactly what rendered the frames.

    Returns figures of the run: frames, seconds, frames_per_s, workers, workers_used, and
    the workers' summed render and write seconds, wall (`render_s`, `write_s`) and CPU
    (`render_cpu_s`, `write_cpu_s`).
    """
    from distributed import as_completed
    from distributed.scheduler import KilledWorker

    todo = writer.todo()
    generator, seed = writer.attrs["generator"], writer.attrs["seed"]
    workers = len(client.scheduler_info(n_workers=-1)["workers"])
    store_key = f"{writer.path}|{writer.frames}|{writer.attrs['created']}"
    frames_of = {}
    for idx in _chunks(todo, chunk):
        fut = client.submit(
            render_chunk,
            str(writer.path),
            store_key,
            generator,
            seed,
            idx,
            pure=False,
            key=f"datagen-{idx[0]}-{time.monotonic_ns()}",
        )
        frames_of[fut] = idx
    futures = list(frames_of)
    done = 0
    clock = dict.fromkeys(("render_s", "write_s", "render_cpu_s", "write_cpu_s"), 0.0)
    pids: set[int] = set()
    next_log = log_every
    t0 = time.perf_counter()
    bar = _progress_bar(len(todo), progress)
    try:
        for fut in as_completed(futures):
            try:
                result = fut.result()
            except OSError as exc:
                raise dataset_os_error(exc, writer.path, "writing") from exc
            except KilledWorker as exc:
                raise TopsegError(
                    f"a worker process died (a crash or out of memory) while rendering frames "
                    f"{frames_of[fut][0]}.. or others it held; complete frames are kept, rerun "
                    "the same command to resume"
                ) from exc
            writer.mark_complete(result["indices"])
            n = len(result["indices"])
            done += n
            for k in clock:
                clock[k] += result[k]
            pids.add(result["pid"])
            rate = done / max(time.perf_counter() - t0, 1e-9)
            bar.update(n)
            bar.set_postfix_str(f"mean {rate:.1f} frames/s", refresh=False)
            if log_every and done / len(todo) >= next_log - 1e-9:
                log.info(
                    "%3.0f%% (%d/%d frames, %.1f frames/s)",
                    100 * done / len(todo),
                    done,
                    len(todo),
                    rate,
                )
                next_log = (np.floor(done / len(todo) / log_every) + 1) * log_every
    finally:
        bar.close()
        client.cancel([f for f in futures if not f.done()])
    seconds = time.perf_counter() - t0
    return {
        "frames": int(done),
        "seconds": seconds,
        "frames_per_s": done / seconds if seconds > 0 else 0.0,
        "workers": workers,
        "workers_used": len(pids),
        **clock,
    }


def make_parent(out: Path) -> None:
    """Create the folder the dataset `out` goes in (with its parents) if it is missing; a
    TopsegError line naming it when it cannot be made."""
    folder = out.absolute().parent
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise TopsegError(f"cannot create the folder {folder}: a file is in the way") from None
    except OSError as exc:
        raise TopsegError(f"cannot create the folder {folder}: {exc.strerror}") from None


def mount_distribution(args: argparse.Namespace, target: str) -> dict | None:
    """`--mounts` / `--sensors` -> a MountDistribution dict (None: the paper's fixed mount)."""
    from topseg.services.batch.datagen.sources import GENERATORS

    kind = getattr(args, "mounts", None) or (
        "random" if target == GENERATORS["synthesis"] else "paper"
    )
    sensors = getattr(args, "sensors", None)
    if kind == "paper":
        if sensors:
            raise TopsegError("--sensors needs --mounts random")
        return None

    d = MountDistribution()
    if sensors:
        d = MountDistribution(d.height_m, d.tilt_deg, weighted_sensors(sensors))
    return d.to_dict()


#: the largest N of a `--sensors NAME:N` weight
MAX_SENSOR_WEIGHT = 100


def weighted_sensors(text: str) -> tuple[str, ...]:
    """`--sensors` text -> the draw list of a MountDistribution: "oak_d:2,kinect_v1" gives
    ("oak_d", "oak_d", "kinect_v1"), a sensor named N times being drawn N times as often."""
    names: list[str] = []
    for item in (s.strip() for s in text.split(",")):
        if not item:
            continue
        name, _, weight = item.partition(":")
        count = 1
        if weight:
            try:
                count = int(weight)
            except ValueError:
                count = 0
            if not 1 <= count <= MAX_SENSOR_WEIGHT:
                raise TopsegError(
                    f"--sensors {item!r}: a weight is a whole number from 1 to "
                    f"{MAX_SENSOR_WEIGHT}, as in oak_d:2"
                )
        names.extend([name.strip()] * count)
    return tuple(names)


def _raise_interrupt(signum, frame):
    raise KeyboardInterrupt


def run(args: argparse.Namespace) -> int:
    """`topseg datagen`: create (or resume) the dataset at `--out` and render its missing frames."""
    if args.datagen_command == "preview":
        from topseg.services.batch.datagen import preview as datagen_preview

        return datagen_preview.run(args)
    if args.datagen_command == "cell-sequence":
        from topseg.services.batch.datagen import cell_sequence

        return cell_sequence.run(args)

    from topseg.services.batch.datagen.sources import (
        generator_config,
        load_factory,
        mount_summary,
        resolve,
    )

    if args.out is None or args.frames is None:
        raise TopsegError("--out and --frames are required (or use `topseg datagen preview PATH`)")
    if args.frames < 1 or args.chunk < 1 or (args.workers is not None and args.workers < 1):
        raise TopsegError("--frames, --chunk and --workers must be >= 1")
    if args.seed < 0:
        raise TopsegError("--seed must be >= 0")
    target = resolve(args.generator)
    load_factory(target)  # a bad name fails here, before a store or a cluster exists
    mounts = mount_distribution(args, target)
    noise = args.noise or ("sensor" if mounts is not None else "gaussian:15")
    noise = noise if noise == "sensor" else parse_noise(noise).spec
    generator = {
        "factory": target,
        "config": generator_config(target, args.mode, noise, args.room, mounts, cell_config(args)),
    }
    attrs = make_attrs(
        seed=args.seed,
        mode=args.mode,
        noise=noise,
        room=args.room,
        generator=generator,
        frames=args.frames,
        mounts=mount_summary(generator),
    )
    make_parent(Path(args.out))
    signal.signal(signal.SIGTERM, _raise_interrupt)
    with DatasetWriter.open(args.out, attrs) as writer:
        had = int(writer.complete.sum())
        if had == writer.frames:
            print(f"{writer.path}: all {writer.frames} frames are already complete")
            return 0
        if had:
            log.info(
                "resuming %s: %d of %d frames already complete", writer.path, had, writer.frames
            )
        try:
            t0 = time.perf_counter()
            with dask_client(args.scheduler, args.workers) as client:
                log.info("Dask ready in %.1f s: %s", time.perf_counter() - t0, client)
                stats = generate(writer, client, chunk=args.chunk, progress=args.progress)
        except KeyboardInterrupt:
            left = int((~writer.complete).sum())
            print(
                f"topseg datagen: interrupted; {writer.frames - left} of {writer.frames} frames complete "
                f"in {writer.path}; rerun the same command to resume",
                file=sys.stderr,
            )
            return 130
    per = 1e3 / max(stats["frames"], 1)
    log.info(
        "per frame on the workers: %.1f ms rendering, %.1f ms writing",
        stats["render_s"] * per,
        stats["write_s"] * per,
    )
    print(
        f"wrote {stats['frames']} frames to {writer.path} in {stats['seconds']:.1f} s: "
        f"{stats['frames_per_s']:.1f} frames/s on {stats['workers']} workers"
        + (f" ({had} were already complete)" if had else "")
    )
    return 0
