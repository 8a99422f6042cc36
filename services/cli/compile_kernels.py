"""Compile numba's kernels into its cache before they are first needed (about two minutes on
2 cores), so that a worker's first start takes seconds rather than minutes; `make install`
and `deploy/install.sh` run it. Run it again after upgrading numba or editing a kernel.

topseg's kernels are compiled by numba on first use and kept in numba's cache (beside the
sources, or in $NUMBA_CACHE_DIR). With the cache empty (a fresh install, a numba upgrade,
an edited kernel), a worker's first start compiles for about two minutes on 2 cores before
it is ready, and the first `topseg datagen` or `topseg train` a minute more. This command
does that work up front, in a few processes at once: each job runs a small piece of real
work of one part of topseg (labelling's forest, its CRF, synthesis, training), so that
numba compiles and caches exactly the kernels that part runs. The last job labels a frame
end to end with every CRF mode and compiles what the others left. `make install` runs it.
"""

from __future__ import annotations

import argparse
import os
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from pathlib import Path

import numba
import numpy as np

from topseg.core import labels as L
from topseg.core.background import warm_up_gate
from topseg.core.camera import KINECT_V1, TopViewMount
from topseg.core.crf import CRFConfig, realtime, segment_crf
from topseg.core.crf.energy import MODES
from topseg.core.errors import TopsegError
from topseg.core.extras import is_installed, needs_extra
from topseg.core.forest.train import TrainConfig, train_forest
from topseg.core.safety.cell import cell_from_dict
from topseg.core.safety.monitor import CellMonitor
from topseg.core.safety.robot import CellRobot
from topseg.core.segmenter import Segmenter, SegmenterConfig
from topseg.core.sensors import SENSORS
from topseg.core.synth.procedural import procedural_frames
from topseg.core.synth.render import Primitives, Triangles, raycast
from topseg.core.synth.synthesis import SynthesisConfig, Synthesizer
from topseg.services.cli.options import int_range


def compile_forest() -> None:
    """Labelling's forest side: the model input, the tree walks, blobs, resolution, smoothing
    (the bundled model, whose features decide the walk kernel's variant)."""
    Segmenter.from_file(None, SegmenterConfig(check_camera=False), crf="none").warm_up()


def compile_crf() -> None:
    """The realtime CRF: its band problem and solve, serial and parallel, on random
    posteriors over a small frame, writable and read-only (as frames off the wire are)."""
    rng = np.random.default_rng(0)
    proba = rng.dirichlet(np.ones(L.NUM_CLASSES), (48, 64)).astype(np.float32)
    depth = rng.integers(1500, 3000, (48, 64)).astype(np.uint16)
    read_only = depth.copy()
    read_only.flags.writeable = False
    for frame in (depth, read_only):
        segment_crf(proba, frame, CRFConfig(mode="realtime"))
    realtime.warm_up(L.NUM_CLASSES)


def compile_synthesis() -> None:
    """Rendering and each supported sensor's noise model (structured light, time of flight,
    stereo), on one small frame each; and the ray caster's triangles (robot arms' meshes)."""
    for sensor in SENSORS:
        k = sensor.intrinsics
        small = k.scaled_to(k.width // 4, k.height // 4)
        mount = TopViewMount(small, 3000.0, 1.0, 0.5, sensor.name)
        Synthesizer(SynthesisConfig(noise="sensor", camera=mount)).render(frame_seed=0)
    corners = np.array([[[-0.5, -0.5, 1.0], [0.5, -0.5, 1.0], [0.0, 0.5, 1.0]]])
    raycast(Primitives.empty(), mount, Triangles(corners, np.ones(1, np.uint8)))


def compile_training() -> None:
    """Training on heights above the floor, as `topseg train` does: sampling, features, the
    splitter, the criterion and the tree builder, on a few small procedural frames."""
    mount = TopViewMount(KINECT_V1.scaled_to(160, 120), 3000.0)
    depth, labels = procedural_frames(np.random.default_rng(0), 3, mount)
    config = TrainConfig(n_trees=1, max_depth=3, frames_per_tree=3, pixels_per_frame=200)
    train_forest(depth, labels, config, mounts=[mount] * len(depth))


def compile_labelling() -> None:
    """A frame labelled end to end with each CRF mode, as the worker and `segment` do, and
    the static cell's background gate: after the jobs above this loads their kernels and
    compiles only what they left."""
    for mode in MODES:
        Segmenter.from_file(None, SegmenterConfig(check_camera=False), crf=mode).warm_up()
    warm_up_gate(np.full((48, 64), 3000, np.uint16))


def compile_safety() -> None:
    """The safety service's: the robot's silhouette and capsules, people's blobs and points,
    the separation (`CellMonitor.warm_up` on a cell of the catalogue's Panda)."""
    cell = cell_from_dict(
        {"cell": "compile", "robot": {"name": "arm", "urdf": "panda"}, "camera": [{"name": "c"}]},
        "topseg compile",
    )
    CellMonitor(cell, CellRobot(cell.robot, Path("."))).warm_up()


#: name -> job (its docstring says what it compiles). These run side by side; `LAST`'s run
#: after them, so that they reuse what these cached instead of compiling it again.
JOBS = {
    "forest": compile_forest,
    "crf": compile_crf,
    "training": compile_training,
    "synthesis": compile_synthesis,
    "safety": compile_safety,
}
LAST = {"labelling": compile_labelling}
#: job -> (the optional package it needs, the extra that installs it)
NEEDS = {"synthesis": ("pybullet", "train"), "safety": ("yourdfpy", "cell")}


def _timed(name: str) -> tuple[str, float]:
    """Run job `name` in this (worker) process; its name and seconds."""
    t0 = time.perf_counter()
    {**JOBS, **LAST}[name]()
    return name, time.perf_counter() - t0


def compile_all(names: list[str], processes: int, report=print) -> dict[str, float]:
    """Run the jobs `names` (of JOBS and LAST), `processes` at a time in fresh processes;
    seconds per job. A job that fails raises in this process with its error."""
    first = [n for n in JOBS if n in names]
    last = [n for n in LAST if n in names]
    seconds: dict[str, float] = {}
    # spawned, not forked: numba's compiler and thread pools are not fork-safe
    with ProcessPoolExecutor(max(1, processes), mp_context=get_context("spawn")) as pool:
        for stage in (first, last):
            for done in as_completed([pool.submit(_timed, n) for n in stage]):
                name, s = done.result()
                seconds[name] = s
                report(f"compiled {name} kernels in {s:.1f} s")
    return seconds


def default_processes() -> int:
    """One process per core this process may run on, up to the jobs that run side by side."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return max(1, min(len(JOBS), cores or 1))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """`topseg compile [JOB ...] [--processes N]`."""
    names = [*JOBS, *LAST]
    parser.add_argument(
        "jobs", nargs="*", metavar="JOB", help=f"what to compile (default: all): {', '.join(names)}"
    )
    parser.add_argument(
        "--processes",
        type=int_range(1, 64),
        default=default_processes(),
        help="jobs compiled at once, one process each (default: one per core this process "
        "may use, up to the jobs that can run at once)",
    )


def installed_jobs(names: list[str], asked: bool, report=print) -> list[str]:
    """`names` less the jobs whose optional package is not installed: each skipped with a
    line naming its extra, or an error when the job was asked for by name."""
    kept = []
    for name in names:
        module, extra = NEEDS.get(name, (None, None))
        if module is None or is_installed(module):
            kept.append(name)
        elif asked:
            raise TopsegError(needs_extra(f"compile {name}", module, extra))
        else:
            report(needs_extra(f"skipped {name} kernels", module, extra))
    return kept


def run(args: argparse.Namespace) -> int:
    """Compile the chosen jobs' kernels into numba's cache and say how long each took."""
    names = args.jobs or [*JOBS, *LAST]
    unknown = [n for n in names if n not in JOBS and n not in LAST]
    if unknown:
        raise TopsegError(f"unknown job {unknown[0]!r}; choose from {', '.join([*JOBS, *LAST])}")
    names = installed_jobs(names, asked=bool(args.jobs))
    where = numba.config.CACHE_DIR or "beside topseg's sources"
    print(f"compiling numba kernels ({', '.join(names)}) into its cache ({where}) ...")
    t0 = time.perf_counter()
    compile_all(names, args.processes)
    print(f"done in {time.perf_counter() - t0:.1f} s")
    return 0
