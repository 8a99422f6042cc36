"""Train a forest on a dataset from `topseg datagen` and write one model file: trees in
parallel on Dask (or `--serial`), the paper's T=5, D=19 recipe by default. A rerun after an
interruption keeps the finished trees and trains only the rest; the model's header holds its
validation scores and what it was trained for (heights, tilt, sensors).

Each tree is a Dask task that opens the dataset itself, trains with its own seed
(`tree_seed(seed, t)`, so any number of workers gives the same trees as a serial run) and
writes its tree atomically to `<out>.parts/tree-<t>.npz`. A rerun after an interruption
keeps the finished trees whose recipe matches and trains only the rest. The last step
scores the forest on a held-out validation split and writes the model with that in its
header.

The model reads heights above the floor (`core.forest.inputs`): every frame is read through
its own mount (`Dataset.mount`, or the dataset's camera for datasets without per-frame
mounts), and the header says so (`"input": "height"`, the feature config) and what it was
trained for (`"trained_for"`: heights, tilt, sensors and resolutions of its frames).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from topseg import __version__
from topseg.core.config import options_of
from topseg.core.errors import ConfigError, TopsegError
from topseg.core.forest.inputs import HEIGHT_INPUT, dataset_mount, header_fields
from topseg.core.forest.inputs import trained_for as describe
from topseg.core.forest.model_file import load_model, save_model
from topseg.core.forest.train_config import TrainConfig
from topseg.core.forest.tree import Forest
from topseg.core.formats.dataset import open_dataset
from topseg.core.metrics import to_json
from topseg.core.scoring import dataset_frames, score
from topseg.core.segmenter import Segmenter
from topseg.services.batch.dask_cluster import dask_client, default_workers
from topseg.services.cli.options import (
    add_setting_arguments,
    finite,
    non_negative_int,
    positive_int,
    settings_from_args,
)

log = logging.getLogger("topseg.train")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """`topseg train`'s options; `TrainJob.from_args` turns them into a job."""
    parser.add_argument(
        "--data", required=True, type=Path, help="dataset written by `topseg datagen`"
    )
    parser.add_argument("--out", required=True, type=Path, help="model file to write")
    g = parser.add_argument_group("forest (defaults: the paper's)")
    add_setting_arguments(g, TrainConfig)
    g.add_argument("--seed", type=non_negative_int, default=0)
    g.add_argument(
        "--validation",
        type=finite(0, 1),
        default=0.1,
        help="fraction of frames held out for the header's metrics",
    )
    g.add_argument("--max-validation-frames", type=non_negative_int, default=64)
    d = parser.add_argument_group("cluster")
    d.add_argument("--scheduler", help="address of an existing Dask scheduler (tcp://host:port)")
    d.add_argument(
        "--workers",
        type=positive_int,
        default=None,
        help="local workers (default: min(trees, cores))",
    )
    d.add_argument("--serial", action="store_true", help="train in this process, no Dask")


def split_frames(n: int, fraction: float, seed: int) -> tuple[list[int], list[int]]:
    """A seeded split of frame positions into (training, validation)."""
    if not 0.0 <= fraction < 1.0:
        raise ValueError(f"--validation must be in [0, 1), got {fraction}")
    order = np.random.default_rng([seed, 0x5EED]).permutation(n)
    n_val = round(n * fraction) if n > 1 else 0
    return sorted(order[n_val:].tolist()), sorted(order[:n_val].tolist())


#: TrainConfig field -> the `topseg train` option that sets it (for error messages)
def option_of(field_name: str) -> str:
    """The `topseg train` option of a `TrainConfig` (or nested) field, else the name."""
    for _, f, option in options_of(TrainConfig):
        if f.name == field_name:
            return f"--{option.flag}"
    return field_name


@dataclass(frozen=True)
class TrainJob:
    """One training run, typed: the dataset, the model file to write, the forest's
    `TrainConfig`, the seed, the validation split and where the trees train (a Dask
    `scheduler`, a local cluster of `workers`, or `serial`ly in this process).

    `topseg train` builds it with `from_args`; `topseg experiment` builds it directly.
    """

    data: Path
    out: Path
    config: TrainConfig
    seed: int = 0
    validation: float = 0.1
    max_validation_frames: int = 64
    scheduler: str | None = None
    workers: int | None = None
    serial: bool = False

    def __post_init__(self) -> None:
        if not 0.0 <= self.validation < 1.0:
            raise ConfigError(f"--validation must be in [0, 1), got {self.validation}")
        if self.max_validation_frames < 0:
            raise ConfigError(
                f"--max-validation-frames must be >= 0, got {self.max_validation_frames}"
            )
        if self.workers is not None and self.workers < 1:
            raise ConfigError(f"--workers must be >= 1, got {self.workers}")
        if self.seed < 0:
            raise ConfigError(f"--seed must be >= 0, got {self.seed}")

    @property
    def trees(self) -> int:
        """Trees in the forest (the config's `n_trees`)."""
        return self.config.n_trees

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> TrainJob:
        """The job `topseg train`'s command line describes (see `add_arguments`); a bad
        value is a ConfigError naming its option."""
        try:
            config = settings_from_args(args, TrainConfig())
        except ValueError as exc:
            field, _, rest = str(exc).partition(" ")
            raise ConfigError(f"{option_of(field)} {rest}") from None
        return cls(
            data=args.data,
            out=args.out,
            config=config,
            seed=args.seed,
            validation=args.validation,
            max_validation_frames=args.max_validation_frames,
            scheduler=args.scheduler,
            workers=args.workers,
            serial=args.serial,
        )


class FrameSubset:
    """Frames `indices` of an (N, H, W) array-like, indexable like an array of them."""

    def __init__(self, frames, indices: list[int]):
        self.frames, self.indices = frames, list(indices)
        self.shape = (len(self.indices), *frames.shape[1:])
        self.dtype = frames.dtype

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, i: int):
        return self.frames[self.indices[int(i)]]


def recipe(job: TrainJob, fingerprint: str) -> dict:
    """What decides every tree: a part file is reused only when its recipe is the same."""
    return {
        "dataset": fingerprint,
        "seed": job.seed,
        "validation": job.validation,
        "config": job.config.to_dict(),
        "input": HEIGHT_INPUT,
    }


def dataset_fingerprint(dataset) -> str:
    """A short hash of the dataset's identity: its attributes and frame count."""
    blob = json.dumps({"attrs": dataset.attrs, "n": len(dataset)}, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def train_one_tree(
    data: str, train_idx: list[int], recipe_: dict, tree: int, part: str, queue=None
) -> str:
    """Dask task: train tree `tree` and write it to `part`; returns the part's path."""
    from topseg.core.forest.train import TrainConfig, train_tree, tree_seed

    ds = open_dataset(data)
    config = TrainConfig.from_dict(recipe_["config"], source=f"the train recipe of {part}")

    def progress(level: int, nodes: int) -> None:
        if queue is not None:
            queue.put([tree, level, nodes])

    t0 = time.perf_counter()
    result = train_tree(
        FrameSubset(ds.depth, train_idx),
        FrameSubset(ds.labels, train_idx),
        config,
        tree_seed(recipe_["seed"], tree),
        progress,
        mounts=lambda k: dataset_mount(ds, train_idx[k]),
    )
    header = {"recipe": recipe_, "tree": tree, "seconds": time.perf_counter() - t0}
    save_model(part, Forest.from_trees([result]), header)
    return part


def _finished_part(part: Path, recipe_: dict):
    """The tree in `part` if it exists, loads whole and was made by the same recipe."""
    if not part.exists():
        return None
    try:
        forest, header = load_model(part)
    except TopsegError as exc:
        log.warning("discarding damaged part %s: %s", part, exc)
        return None
    if header.get("recipe") != recipe_:
        log.info("discarding part %s: made by another recipe", part)
        return None
    return forest.tree(0)


def run(args: argparse.Namespace) -> int:
    """`topseg train`: the command line as a `TrainJob`, trained on its dataset's split."""
    job = TrainJob.from_args(args)
    ds = open_dataset(job.data)
    train_idx, val_idx = split_frames(len(ds), job.validation, job.seed)
    if not train_idx:
        raise TopsegError(f"{job.data} has no frames to train on")
    train_on(job, ds, train_idx, val_idx)
    return 0


def train_on(
    job: TrainJob,
    ds,
    train_idx: list[int],
    val_idx: list[int],
    fingerprint: str | None = None,
) -> float:
    """Train `job` on frames `train_idx` of the open dataset `ds`, score `val_idx`, write
    `job.out`; resumable through `<out>.parts`. Returns the training seconds.

    `topseg experiment` trains on a chosen subset this way, naming that subset's identity
    in `fingerprint` (default: the whole dataset's).
    """
    recipe_ = recipe(job, fingerprint or dataset_fingerprint(ds))
    parts_dir = job.out.with_name(job.out.name + ".parts")
    try:
        parts_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise TopsegError(
            f"cannot write {job.out}: cannot create {parts_dir}: {exc.strerror}"
        ) from None
    parts = [parts_dir / f"tree-{t}.npz" for t in range(job.trees)]
    trees = {
        t: tree for t, p in enumerate(parts) if (tree := _finished_part(p, recipe_)) is not None
    }
    if trees:
        log.info("resuming: %d of %d trees already trained", len(trees), job.trees)
    todo = [t for t in range(job.trees) if t not in trees]

    t0 = time.perf_counter()
    if todo:
        try:
            _train_trees(job, train_idx, recipe_, todo, parts)
        except OSError as exc:  # a tree part could not be written (full disk, folder gone)
            done = sum(_finished_part(p, recipe_) is not None for p in parts)
            raise TopsegError(
                f"cannot write {exc.filename or parts_dir}: {exc.strerror or exc}; {done} of "
                f"{job.trees} trees are kept in {parts_dir}: rerun the same command to resume"
            ) from None
        for t in todo:
            trees[t] = _finished_part(parts[t], recipe_)
            if trees[t] is None:
                raise TopsegError(f"tree {t} did not come back whole from {parts[t]}")
    seconds = time.perf_counter() - t0
    try:
        _write_model(job, ds, val_idx, recipe_, [trees[t] for t in range(job.trees)], seconds)
    except OSError as exc:
        raise TopsegError(
            f"cannot write {job.out}: {exc.strerror or exc}; all {job.trees} trees are kept in "
            f"{parts_dir}: rerun the same command to write the model"
        ) from None
    # the parts, and the temp files of part writes a kill -9 cut short (atomic_write's)
    try:
        for p in [*parts, *parts_dir.glob(".tree-*.npz.*.tmp")]:
            p.unlink(missing_ok=True)
        parts_dir.rmdir()
    except OSError as exc:  # the model is written; leftovers are only clutter
        log.warning("could not remove %s: %s", parts_dir, exc.strerror or exc)
    return seconds


def _train_trees(job: TrainJob, train_idx, recipe_, todo, parts) -> None:
    """Train the trees in `todo`, serially or on Dask, with a progress bar per tree."""
    from tqdm import tqdm

    levels = recipe_["config"]["max_depth"] + 1  # levels 0..max_depth
    bars = {
        t: tqdm(total=levels, desc=f"tree {t}", unit="level", position=i, leave=True)
        for i, t in enumerate(todo)
    }

    def advance(tree: int, level: int, nodes: int) -> None:
        bar = bars[tree]
        bar.set_postfix(nodes=nodes)
        bar.update(max(0, level + 1 - bar.n))

    try:
        if job.serial:
            for t in todo:
                _serial_tree(job, train_idx, recipe_, t, str(parts[t]), advance)
        else:
            _dask_trees(job, train_idx, recipe_, todo, parts, advance)
    finally:
        for bar in bars.values():
            bar.close()


class _CallbackQueue:
    def __init__(self, fn):
        self.fn = fn

    def put(self, item):
        self.fn(*item)


def _serial_tree(job: TrainJob, train_idx, recipe_, t, part, advance) -> None:
    train_one_tree(str(job.data), train_idx, recipe_, t, part, _CallbackQueue(advance))


def _dask_trees(job: TrainJob, train_idx, recipe_, todo, parts, advance) -> None:
    """Train the trees in `todo` as Dask tasks: on `job.scheduler`, or on a local cluster of
    `job.workers` processes (default: one per tree, at most one per core)."""
    from distributed import Queue

    workers = job.workers or max(1, min(len(todo), default_workers()))
    with dask_client(job.scheduler, None if job.scheduler else workers) as client:
        queue = Queue(f"topseg-train-{uuid.uuid4().hex}", client=client)
        futures = [
            client.submit(
                train_one_tree,
                str(job.data.resolve()),
                train_idx,
                recipe_,
                t,
                str(parts[t].resolve()),
                queue,
                key=f"tree-{t}-{uuid.uuid4().hex[:8]}",
                pure=False,
            )
            for t in todo
        ]
        while not all(f.done() for f in futures):
            for item in queue.get(batch=True):
                advance(*item)
            time.sleep(0.5)
        for item in queue.get(batch=True):
            advance(*item)
        for f in futures:
            f.result()  # re-raise a worker's error here


def _write_model(args, ds, val_idx, recipe_, trees, seconds) -> None:
    from topseg.core.forest.train import TrainConfig

    forest = Forest.from_trees(trees)
    config = TrainConfig.from_dict(recipe_["config"], source="the train recipe")
    inputs = header_fields(config.features, trained_for(ds, train_idx_of(ds, val_idx)))
    # the forest's argmax through the one Segmenter, each frame read through its own mount
    segmenter = Segmenter(forest, inputs, crf="none")
    frames = dataset_frames(ds, val_idx[: args.max_validation_frames])
    acc = score(segmenter, frames).crf
    validation = json.loads(to_json(acc.scores())) if val_idx else None  # NaN -> null
    header = {
        **inputs,
        "made_by": f"topseg {__version__} train",
        "recipe": recipe_,
        "dataset": {"path": str(args.data), "frames": len(ds), "attrs": ds.attrs},
        "train_seconds": round(seconds, 1),
        "validation": {
            "frames": min(len(val_idx), args.max_validation_frames),
            "scores": validation,
        },
    }
    save_model(args.out, forest, header)
    if validation:
        print(
            f"wrote {args.out}: {len(trees)} trees; validation on {header['validation']['frames']} frames: "
            f"mAP {_fmt(validation['mAP'])}  mAR {_fmt(validation['mAR'])}  "
            f"avg F1 {_fmt(validation['avg_f1'])}"
        )
    else:
        print(f"wrote {args.out}: {len(trees)} trees (no validation frames)")


def train_idx_of(ds, val_idx: list[int]) -> list[int]:
    """The frame positions of `ds` not in `val_idx` (what the trees were trained on)."""
    held = set(val_idx)
    return [i for i in range(len(ds)) if i not in held]


def trained_for(ds, indices: list[int]) -> dict:
    """What a model trained on frames `indices` of `ds` was trained for (`inputs.trained_for`):
    the synthesis' mount distribution when the dataset records one, else the range of the
    frames' own mounts."""
    summary = getattr(ds, "mount_summary", None)
    if isinstance(ds.attrs.get("mounts"), dict) and callable(summary):
        return summary()
    return describe([dataset_mount(ds, i) for i in indices] or [dataset_mount(ds, 0)])


def _fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.3f}"
