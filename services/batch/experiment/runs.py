"""The pieces one point of `topseg experiment` is made of: scales, cached datasets, a trained
model, and its scores on the held-out test set.

- A *dataset recipe* (generator, mode, noise, theta', seed) names a synthetic dataset in the
  data cache; its frame count is not part of the name, so the set made for the largest F
  serves every smaller F through its first F frames (the store grows, `topseg datagen`
  style, when a point needs more).
- A *model* is trained on the first F frames of a recipe's dataset with the scale's forest
  parameters; it is kept under OUT/models/ by a hash of everything that decides it, so
  experiments that need the same model (table and frames at F = 1600) train it once.
  Training resumes through train's `<model>.parts`.
- A *point* is a model scored on the test set: forest alone and forest + CRF, written
  atomically as JSON; a rerun skips points whose JSON is there with the same recipe.
"""

from __future__ import annotations

import hashlib
import json
import logging
from dataclasses import asdict, dataclass, replace
from pathlib import Path

from topseg.core import metrics
from topseg.core.atomic import atomic_write
from topseg.core.config import with_options
from topseg.core.errors import TopsegError
from topseg.core.forest.train_config import TrainConfig
from topseg.core.formats.dataset import DatasetWriter, make_attrs, open_dataset
from topseg.core.scoring import dataset_frames
from topseg.core.scoring import score as score_frames
from topseg.core.segmenter import Segmenter
from topseg.core.synth.noise import parse_noise
from topseg.core.synth.synthesis import SynthesisConfig
from topseg.services.batch import train
from topseg.services.batch.dask_cluster import dask_client
from topseg.services.batch.datagen import generate, render_chunk
from topseg.services.batch.datagen.sources import GENERATORS
from topseg.services.batch.train import TrainJob

log = logging.getLogger("topseg.experiment")

TRAIN_NOISE = "gaussian:15"  # the paper's best training noise (mm; docs/explanation/noise.md)
TEST_NOISE = "kinect"  # the held-out set: realistic Kinect v1 noise
TEST_SEED_OFFSET = 1000  # the test set's dataset seed is --seed + this: other scenes
DEFAULT_THETA = 0.30  # the density's default theta' (DensityConfig)
FEATURE_BUDGET_GB = 6.0  # default GB of features the training workers hold side by side


@dataclass(frozen=True)
class Scale:
    """Forest and data sizes of one scale; `sweeps` may shorten an experiment's x values."""

    name: str
    trees: int
    depth: int
    features: int  # PC
    responses: int  # R
    thresholds: int  # K
    frames: int  # F per tree unless swept
    pixels_per_frame: int
    test_frames: int
    serial: bool = False  # train in this process (tiny: no cluster start per point)
    sweeps: tuple[tuple[str, tuple], ...] = ()

    def sweep(self, experiment: str, default: tuple) -> tuple:
        """The x values of `experiment` at this scale: its own sweep, else `default`."""
        return dict(self.sweeps).get(experiment, default)

    def describe(self) -> str:
        """The scale's sizes in one line, for the run's first output."""
        return (
            f"scale {self.name}: T={self.trees} D={self.depth} PC={self.features} "
            f"R={self.responses} K={self.thresholds} F={self.frames}/tree (unless swept), "
            f"{self.pixels_per_frame} px/frame; test set {self.test_frames} modeled frames "
            f"({TEST_NOISE} noise); training noise {TRAIN_NOISE} unless swept"
        )


SCALES: dict[str, Scale] = {
    "tiny": Scale(
        "tiny",
        trees=1,
        depth=8,
        features=40,
        responses=10,
        thresholds=10,
        frames=4,
        pixels_per_frame=300,
        test_frames=2,
        serial=True,
        sweeps=(
            ("noise", (0, 15)),
            ("features", (75, 150)),
            ("frames", (2, 4)),
            ("overlap", (0, 30)),
        ),
    ),
    "quick": Scale(
        "quick",
        trees=2,
        depth=14,
        features=100,
        responses=30,
        thresholds=30,
        frames=200,
        pixels_per_frame=1000,
        test_frames=40,
        sweeps=(("frames", (40, 200, 400)),),
    ),
    "paper": Scale(
        "paper",
        trees=5,
        depth=19,
        features=300,
        responses=100,
        thresholds=100,
        frames=1600,
        pixels_per_frame=2000,
        test_frames=100,
    ),
}


def short_hash(obj) -> str:
    """12 hex digits of the SHA-256 of `obj` as canonical JSON: a cache key."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True).encode()).hexdigest()[:12]


# ---------------------------------------------------------------- datasets


@dataclass(frozen=True)
class DataRecipe:
    """What makes a synthetic dataset (its size apart)."""

    mode: str = "modeled"
    noise: str = TRAIN_NOISE
    theta: float | None = None  # theta' as a fraction; None = the density's default
    seed: int = 0

    def normalised(self) -> DataRecipe:
        """The same recipe spelled one way (noise spec normalised, the default theta as None)."""
        theta = None if self.theta is None or abs(self.theta - DEFAULT_THETA) < 1e-9 else self.theta

        return replace(self, noise=parse_noise(self.noise).spec, theta=theta)

    def name(self) -> str:
        """The dataset's folder name in the cache: readable parts and a hash of the recipe."""
        r = self.normalised()
        noise = r.noise.replace(":", "")
        theta = "" if r.theta is None else f"-theta{round(100 * r.theta)}"
        return f"{r.mode}-{noise}{theta}-seed{r.seed}-{short_hash(asdict(r))[:8]}.zarr"

    def attrs(self, frames: int) -> dict:
        """The dataset attributes `topseg datagen` would write for this recipe and size."""
        r = self.normalised()
        # the paper's fixed mount (mounts=None, camera PAPER_MOUNT), so the experiments stay
        # comparable with the paper's; new training data draws mounts (`topseg datagen`)
        synth = SynthesisConfig(mode=r.mode, noise=r.noise, theta_max=r.theta, mounts=None)
        generator = {"factory": GENERATORS["synthesis"], "config": synth.to_dict()}
        return make_attrs(
            seed=r.seed, mode=r.mode, noise=r.noise, room=None, generator=generator, frames=frames,
            camera=synth.camera.to_dict(), mounts=synth.mount_summary(),
        )  # fmt: skip


def ensure_dataset(
    cache: Path, recipe: DataRecipe, frames: int, workers: int | None, serial: bool = False
):
    """The cached dataset of `recipe` with at least `frames` complete frames (rendered or
    grown on a local Dask cluster when short, or in this process when `serial`); returns it
    opened for reading."""
    path = cache / recipe.name()
    if (path / "zarr.json").exists():
        ds = open_dataset(path)
        if len(ds) >= frames and bool(ds.complete[:frames].all()):
            return ds
        frames = max(frames, int(ds.attrs["frames"]))
    cache.mkdir(parents=True, exist_ok=True)
    with DatasetWriter.open(path, recipe.attrs(frames)) as writer:
        todo = len(writer.todo())
        if todo and serial:
            print(f"  data: rendering {todo} frames of {path.name} in this process", flush=True)
            a = writer.attrs
            indices = writer.todo().tolist()
            key = f"{writer.path}|{writer.frames}|{a['created']}"  # as datagen.generate's
            render_chunk(str(writer.path), key, a["generator"], a["seed"], indices)
            writer.mark_complete(indices)
        elif todo:
            print(f"  data: rendering {todo} frames of {path.name}", flush=True)
            with dask_client(None, workers) as client:
                stats = generate(writer, client, progress=None, log_every=0)
            print(
                f"  data: {stats['frames']} frames in {stats['seconds']:.0f} s "
                f"({stats['frames_per_s']:.1f} frames/s)",
                flush=True,
            )
    return open_dataset(path)


# ---------------------------------------------------------------- models


@dataclass(frozen=True)
class ModelRecipe:
    """A forest trained on the first `frames` frames of `data`'s dataset."""

    data: DataRecipe
    frames: int
    trees: int
    depth: int
    features: int
    responses: int
    thresholds: int
    pixels_per_frame: int
    split: str = "linear"
    seed: int = 0

    def to_dict(self) -> dict:
        """The recipe as plain data, its dataset recipe normalised (what `key` hashes)."""
        d = asdict(self)
        d["data"] = asdict(self.data.normalised())
        return d

    def key(self) -> str:
        """The model's name in OUT/models/: a hash of everything that decides it."""
        return short_hash(self.to_dict())

    def train_config(self) -> TrainConfig:
        """The forest's `TrainConfig`: the recipe's fields are named as `topseg train`'s
        options (`frames` is --frames-per-tree); the paper's defaults for the rest."""
        return with_options(TrainConfig(), {**asdict(self), "frames_per_tree": self.frames})

    def train_job(
        self, data_path: Path, out: Path, workers: int | None, serial: bool,
        budget_gb: float = FEATURE_BUDGET_GB,
    ):  # fmt: skip
        """The `train.TrainJob` that trains this model into `out` (no validation split); as
        many Dask workers as asked for whose trees' features (int16) fit in `budget_gb`
        together."""
        per_tree = self.frames * self.pixels_per_frame * self.features * 2
        fit = max(1, int(budget_gb * 1e9 // max(per_tree, 1)))
        return TrainJob(
            data=data_path,
            out=out,
            config=self.train_config(),
            seed=self.seed,
            validation=0.0,
            max_validation_frames=0,
            workers=max(1, min(workers or 2, fit, self.trees)),
            serial=serial,
        )


def ensure_model(
    out: Path, cache: Path, recipe: ModelRecipe, workers, serial: bool,
    budget_gb: float = FEATURE_BUDGET_GB,
) -> Path:  # fmt: skip
    """The model file of `recipe` under OUT/models/, trained (or its training resumed) when
    missing; the dataset is made or grown first."""
    path = out / "models" / f"model-{recipe.key()}.npz"
    if path.exists():
        return path
    ds = ensure_dataset(cache, recipe.data, recipe.frames, workers, serial)
    path.parent.mkdir(parents=True, exist_ok=True)
    job = recipe.train_job(ds.path, path, workers, serial, budget_gb)
    print(
        f"  train: {recipe.trees} trees on the first {recipe.frames} frames of {ds.path.name} "
        f"({'serial' if serial else f'{job.workers} Dask worker(s)'})",
        flush=True,
    )
    train.train_on(job, ds, list(range(recipe.frames)), [], fingerprint=recipe.key())
    return path


# ---------------------------------------------------------------- scoring


def test_recipe(seed: int) -> DataRecipe:
    """The held-out test set's recipe: modeled Kinect-noise scenes of other seeds."""
    return DataRecipe(mode="modeled", noise=TEST_NOISE, seed=seed + TEST_SEED_OFFSET)


def score(model_path: Path, ds, frames: int, crf_mode: str) -> dict:
    """Forest-only and forest + CRF scores of a model on the first `frames` test frames."""
    from tqdm import tqdm

    segmenter = Segmenter.from_file(model_path, crf=crf_mode)
    pairs = tqdm(
        dataset_frames(ds, range(frames)),
        total=frames,
        desc="  score",
        unit="frame",
        disable=None,
        leave=False,
    )
    result = score_frames(segmenter, pairs)
    return {
        # the paper's ten-class tables, whatever classes the model knows
        "forest": json.loads(metrics.to_json(metrics.ten_class_scores(result.forest.scores()))),
        "crf": json.loads(metrics.to_json(metrics.ten_class_scores(result.crf.scores()))),
        "crf_mode": crf_mode,
        "test_frames": frames,
        "ms_per_frame": {k: round(v, 2) for k, v in result.ms_per_frame().items()},
    }


def point_recipe(model: ModelRecipe, test: DataRecipe, test_frames: int, crf_mode: str) -> dict:
    """Everything that decides a point's scores; a finished point is reused only when equal."""
    return {
        "model": model.to_dict(),
        "test": asdict(test.normalised()),
        "test_frames": test_frames,
        "crf": crf_mode,
    }


def load_point(path: Path, recipe: dict) -> dict | None:
    """The finished point at `path` if it was made by `recipe`."""
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return doc if doc.get("recipe") == recipe else None


def scored_elsewhere(out: Path, recipe: dict) -> dict | None:
    """A point another experiment in `out` already scored with the same recipe (the same
    model on the same test frames: table's points are frames' F = 1600 points), or None."""
    for path in sorted((out / "points").glob("*/*.json")):
        doc = load_point(path, recipe)
        if doc is not None:
            return doc
    return None


def write_json(path: Path, doc: dict) -> None:
    """Write `doc` as indented JSON to `path` atomically (its folder made when missing)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path) as f:
        f.write((json.dumps(doc, indent=1) + "\n").encode())


def check_positive(name: str, value: int | None) -> None:
    """A TopsegError when option `name` is given and below 1."""
    if value is not None and value < 1:
        raise TopsegError(f"{name} must be >= 1, got {value}")
