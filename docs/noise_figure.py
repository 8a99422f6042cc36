"""Regenerate the figures and numbers of docs/noise.md.

    .venv/bin/python docs/noise_figure.py [--real ../shared/data/real-kinect-v1]

Compares the Kinect v1 noise model with the real Kinect v1 frames two ways: on the real
frames' own geometry (each real frame's holes filled and its noise median-filtered away,
then the model applied) and on synthetic top-view scenes. Writes docs/img/noise.png and
docs/img/noise_examples.png and prints the tables docs/noise.md quotes.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
EDGES = np.arange(1000, 5001, 500)


def load_real(folder: Path) -> list[tuple[str, np.ndarray]]:
    from PIL import Image

    frames = []
    for path in sorted(folder.glob("*_depth.png")):
        d = np.asarray(Image.open(path))
        if d.dtype != np.uint16 or d.shape != (480, 640):
            raise SystemExit(f"{path}: expected a 640x480 16-bit depth PNG")
        frames.append((path.stem.replace("_depth", ""), d))
    if not frames:
        raise SystemExit(f"no *_depth.png in {folder}")
    return frames


def clean_geometry(depth: np.ndarray) -> np.ndarray:
    """The scene behind a real frame: holes take their nearest measured depth, and a 5x5
    median removes the sensor's noise and flying pixels while keeping the jumps."""
    from scipy import ndimage

    missing = depth == 0
    idx = ndimage.distance_transform_edt(missing, return_distances=False, return_indices=True)
    filled = depth[tuple(idx)]
    return ndimage.median_filter(filled, size=5).astype(np.uint16)


def colour_depth(d: np.ndarray, lo: float, hi: float) -> np.ndarray:
    g = (255 * (1 - (d.astype(float) - lo) / (hi - lo))).clip(0, 255).astype(np.uint8)
    rgb = np.stack([g, g, g], -1)
    rgb[d == 0] = (220, 30, 30)
    return rgb


def main() -> None:
    import warnings

    import matplotlib

    warnings.filterwarnings("ignore", message="All-NaN slice")  # depth bins a source lacks

    matplotlib.use("Agg")
    import depth_stats  # docs/depth_stats.py, beside this script
    import matplotlib.pyplot as plt

    from topseg.core import labels
    from topseg.core.synth.noise import GaussianNoise, KinectNoise
    from topseg.core.synth.synthesis import SynthesisConfig, Synthesizer

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--real", type=Path, default=HERE.parent.parent / "shared" / "data" / "real-kinect-v1"
    )
    ap.add_argument("--frames", type=int, default=12, help="synthetic top-view frames")
    args = ap.parse_args()

    model = KinectNoise()
    fb = model.fb
    rng = np.random.default_rng(0)
    real = load_real(args.real)
    modelled = [(name, model.apply(clean_geometry(d), rng)) for name, d in real]

    with Synthesizer(SynthesisConfig(noise="none", seed=1)) as synth:
        clean_top = [synth.render(i) for i in range(args.frames)]
    top = [model.apply(f.depth, rng) for f in clean_top]

    def table(frames):
        rows = [depth_stats.summary(d, fb) for _, d in frames]
        keys = rows[0].keys()
        return {k: float(np.nanmean([r.get(k, np.nan) for r in rows])) for k in keys}

    stats = {
        "real": table(real),
        "model on real geometry": table(modelled),
        "model on top-view scenes": table([("", d) for d in top]),
    }
    spacing = {
        "real": np.nanmedian([depth_stats.level_spacing(d, EDGES) for _, d in real], axis=0),
        "model on real geometry": np.nanmedian(
            [depth_stats.level_spacing(d, EDGES) for _, d in modelled], axis=0
        ),
        "model on top-view scenes": np.nanmedian(
            [depth_stats.level_spacing(d, EDGES) for d in top], axis=0
        ),
    }
    rough = {
        "real": np.nanmedian([depth_stats.roughness(d, EDGES) for _, d in real], axis=0),
        "model on real geometry": np.nanmedian(
            [depth_stats.roughness(d, EDGES) for _, d in modelled], axis=0
        ),
        "model on top-view scenes": np.nanmedian(
            [depth_stats.roughness(d, EDGES) for d in top], axis=0
        ),
    }

    # --- figure 1: real against model ------------------------------------------------------
    z = (EDGES[1:] + EDGES[:-1]) / 2
    zz = np.linspace(1.0, 5.0, 100)
    fig = plt.figure(figsize=(15, 9.2))
    name, d = real[1]
    panels = [
        (colour_depth(d, 1500, 5000), f"real Kinect v1 ({name})"),
        (colour_depth(modelled[1][1], 1500, 5000), "model on the same geometry"),
        (colour_depth(top[0], 1500, 3600), "model on a synthetic top-view scene"),
    ]
    for i, (img, title) in enumerate(panels):
        ax = fig.add_subplot(2, 3, i + 1)
        ax.imshow(img)
        ax.set_title(title + "  (red: no depth)", fontsize=10)
        ax.axis("off")
    marks = {"real": "o", "model on real geometry": "x", "model on top-view scenes": "^"}
    ax = fig.add_subplot(2, 3, 4)
    for k, v in spacing.items():
        ax.plot(z / 1000, v, marks[k], label=k, ms=7)
    ax.plot(zz, 1000 * zz**2 / (model.subpixel * fb), "k-", lw=1, label="z^2 / (8 f b)")
    ax.set(
        xlabel="depth z (m)", ylabel="gap between depth levels (mm)", title="disparity quantisation"
    )
    ax.legend(fontsize=8)
    ax = fig.add_subplot(2, 3, 5)
    for k, v in rough.items():
        ax.plot(z / 1000, v, marks[k], label=k, ms=7)
    ax.plot(zz, [model.sigma_mm(x) for x in zz], "k-", lw=1, label="model sigma (noise + steps)")
    ax.plot(zz, 1.425 * zz**2, "k:", lw=1, label="1.425e-3 z^2 (Khoshelham 2012)")
    ax.set(
        xlabel="depth z (m)",
        ylabel="std about a local plane (mm)",
        title="noise on flat patches (8x8)",
    )
    ax.legend(fontsize=8)
    ax = fig.add_subplot(2, 3, 6)
    keys = [("shadow_far_on_left", "gaps with far side left"), ("shadow_left_extra_px", "gap width - shadow (px)/10"),
            ("edge_missing", "jump pixels missing"), ("edge_flying", "jump pixels flying")]  # fmt: skip
    x = np.arange(len(keys))
    for j, (k, _) in enumerate(stats.items()):
        vals = [stats[k][key] / (10 if key.endswith("extra_px") else 1) for key, _ in keys]
        ax.bar(x + (j - 1) * 0.27, vals, width=0.27, label=k)
    ax.set_xticks(x, [lab for _, lab in keys], rotation=15, fontsize=8)
    ax.set_title("edges and shadows", fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    (HERE / "img").mkdir(exist_ok=True)
    fig.savefig(HERE / "img" / "noise.png", dpi=80)

    # --- figure 2: one synthetic frame under each noise model --------------------------------
    f = clean_top[0]
    fig, axes = plt.subplots(2, 3, figsize=(15, 7.6))
    variants = [("clean", f.depth), ("gaussian:15 (the paper's best)", GaussianNoise(15).apply(f.depth, rng)),
                ("gaussian:100", GaussianNoise(100).apply(f.depth, rng)), ("kinect", top[0])]  # fmt: skip
    for ax, (title, d) in zip(axes.ravel(), variants, strict=False):
        ax.imshow(colour_depth(d, 1500, 3600))
        ax.set_title(title)
        ax.axis("off")
    lab = f.labels.copy()
    lab[top[0] == 0] = labels.NO_DEPTH
    axes.ravel()[4].imshow(labels.colorize(f.labels))
    axes.ravel()[4].set_title("labels")
    axes.ravel()[5].imshow(labels.colorize(lab))
    axes.ravel()[5].set_title("labels after kinect noise (black: no depth)")
    for ax in axes.ravel()[4:]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(HERE / "img" / "noise_examples.png", dpi=70)

    print(
        json.dumps(
            {k: {kk: round(vv, 3) for kk, vv in v.items()} for k, v in stats.items()}, indent=1
        )
    )
    print("depth bin centres (m):", (z / 1000).round(2).tolist())
    for name, table_ in (("level gap (mm)", spacing), ("roughness (mm)", rough)):
        print(name)
        for k, v in table_.items():
            print(f"  {k:26s}", np.round(v, 1).tolist())
    print(
        "model: step",
        [round(model.depth_step_mm(x / 1000), 1) for x in z],
        "sigma",
        [round(model.sigma_mm(x / 1000), 1) for x in z],
    )


if __name__ == "__main__":
    main()
