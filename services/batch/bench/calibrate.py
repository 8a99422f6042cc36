"""Mount calibration on rendered frames: `topseg bench calibrate`.

For each of `--mounts` random mounts (height U[2.4, 4.5] m, pitch and roll U[-10, 10] deg, a
sensor from `core.sensors` with its intrinsics; the training data's `MountDistribution`), it
renders `--frames` scenes of people and furniture from that mount with the sensor's own noise
(`Synthesizer`, noise "sensor"), estimates the mount from them (`core.calibration`) and
compares it with the truth. Reported: height |error| (mm), pitch and roll |error| (deg), each
max and p95; the share of mounts within 2 cm and within 0.5 deg; how much of the floor the
scenes covered; and the refusals (CalibrationError), which count as failures.

The target (docs/results.md): height within 2 cm, pitch and roll within 0.5 deg, over at least 50 mounts
with people and furniture covering up to 40 % of the floor.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from topseg.core import labels
from topseg.core.calibration import CalibrationError, estimate_mount
from topseg.core.errors import TopsegError
from topseg.core.metrics import percentile
from topseg.core.synth.density import DensityConfig
from topseg.core.synth.synthesis import MountDistribution, SynthesisConfig, Synthesizer
from topseg.services.cli.options import int_range, non_negative_int

#: a pixel counts as floor in the truth when its true height is below this (mm)
FLOOR_BAND_MM = 60.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """--mounts, --frames per mount, --seed, --max-objects."""
    parser.add_argument(
        "--mounts", type=int_range(1, 100000), default=50, help="random mounts (default 50)"
    )
    parser.add_argument(
        "--frames",
        type=int_range(1, 10000),
        default=5,
        help="frames per mount to calibrate from (default 5)",
    )
    parser.add_argument("--seed", type=non_negative_int, default=0)
    parser.add_argument(
        "--max-objects",
        type=int_range(1, 100),
        default=7,
        help="furniture per scene drawn from 1..N (people come with the scenes)",
    )


def floor_cover(depth, labels_img, mount) -> float:
    """Share of the floor area in view covered by people and furniture (from the truth)."""
    fg = np.isin(labels_img, (*labels.HUMAN_IDS, *labels.FURNITURE_IDS))
    h = mount.height_map_mm(depth)
    with np.errstate(invalid="ignore"):
        floor = (labels_img == labels.BACKGROUND) & (np.abs(h) < FLOOR_BAND_MM)
    n = int(fg.sum() + floor.sum())
    return float(fg.sum()) / n if n else 0.0


def measure(args: argparse.Namespace) -> dict:
    """Errors of the estimated mounts against the true ones, over `--mounts` mounts."""
    if args.mounts < 1 or args.frames < 1 or args.max_objects < 1:
        raise TopsegError("--mounts, --frames and --max-objects must be at least 1")
    mounts = MountDistribution()  # 2.4-4.5 m, +-10 deg, every supported sensor
    density = DensityConfig(n_objects=(1, args.max_objects))
    cfg = SynthesisConfig(noise="sensor", seed=args.seed, density=density)
    rng = np.random.default_rng(args.seed)
    dh, dp, dr, covers, seconds, failures, sensors = [], [], [], [], [], [], []
    with Synthesizer(cfg, warm=False) as synth:
        for m in range(args.mounts):
            mount = mounts.draw(rng)
            frames = []
            for f in range(args.frames):
                scene_rng, noise_rng = synth.rngs(1000 * m + f)
                scene = synth.density.sample(scene_rng, mount)
                frame = synth.render_scene(scene, noise_rng)
                frames.append(frame.depth)
                covers.append(floor_cover(frame.depth, frame.labels, mount))
            t0 = time.perf_counter()
            try:
                est = estimate_mount(frames, mount.intrinsics, mount.sensor)
            except CalibrationError as exc:
                failures.append(f"{mount.sensor} {mount.height_mm:.0f} mm: {exc}")
                continue
            finally:
                seconds.append(time.perf_counter() - t0)
            sensors.append(mount.sensor)
            dh.append(abs(est.mount.height_mm - mount.height_mm))
            dp.append(abs(est.mount.pitch_deg - mount.pitch_deg))
            dr.append(abs(est.mount.roll_deg - mount.roll_deg))
    dh_a, dp_a, dr_a = (np.asarray(v, np.float64) for v in (dh, dp, dr))
    ok = len(dh)
    out: dict = {
        "mounts": args.mounts,
        "frames_per_mount": args.frames,
        "estimated": ok,
        "failures": len(failures),
    }
    if ok:
        out |= {
            "height_err_mm_max": round(float(dh_a.max()), 2),
            "height_err_mm_p95": round(percentile(dh_a, 95), 2),
            "pitch_err_deg_max": round(float(dp_a.max()), 3),
            "pitch_err_deg_p95": round(percentile(dp_a, 95), 3),
            "roll_err_deg_max": round(float(dr_a.max()), 3),
            "roll_err_deg_p95": round(percentile(dr_a, 95), 3),
            "share_height_within_2cm": round(float(np.mean(dh_a <= 20.0)), 3),
            "share_angles_within_0.5deg": round(float(np.mean(np.maximum(dp_a, dr_a) <= 0.5)), 3),
        }
        for name in sorted(set(sensors)):
            sel = np.array([s == name for s in sensors])
            out[f"height_err_mm_max[{name}]"] = round(float(dh_a[sel].max()), 2)
    out |= {
        "share_all_within_bar": round(
            float(np.sum((dh_a <= 20.0) & (np.maximum(dp_a, dr_a) <= 0.5))) / args.mounts, 3
        ),
        "floor_cover_mean": round(float(np.mean(covers)), 3),
        "floor_cover_max": round(float(np.max(covers)), 3),
        "frames_cover_over_30pct": round(float(np.mean(np.asarray(covers) > 0.30)), 3),
        "estimate_s_p50": round(percentile(np.asarray(seconds), 50), 3),
    }
    if failures and args.json:
        out["failure_reasons"] = failures
    return out
