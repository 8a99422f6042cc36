"""Regenerate the figures and numbers of docs/explanation/noise.md.

    .venv/bin/python docs/noise_figure.py [--real ../shared/data/real-kinect-v1]
    .venv/bin/python docs/noise_figure.py --sensors-only

Compares the Kinect v1 noise model with the real Kinect v1 frames two ways: on the real
frames' own geometry (each real frame's holes filled and its noise median-filtered away,
then the model applied) and on synthetic top-view scenes. Writes docs/img/noise.png and
docs/img/noise_examples.png and prints the tables docs/explanation/noise.md quotes. Then (alone with
`--sensors-only`) renders one scene through each sensor of core/sensors.py and each effect
of the time-of-flight and stereo models beside what it models: docs/img/noise_sensors.png
and docs/img/noise_effects.png.
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
    ap.add_argument(
        "--sensors-only", action="store_true", help="only the time-of-flight / stereo figures"
    )
    args = ap.parse_args()
    if args.sensors_only:
        sensor_figures(plt)
        return

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
    sensor_figures(plt)


# --- time of flight and active stereo: docs/img/noise_sensors.png, noise_effects.png --------


def _scene_primitives(seed: int = 3, frames: int = 8):
    """The primitives of the synthetic frame (of the first `frames`) showing the most head."""
    from topseg.core import labels
    from topseg.core.synth.synthesis import SynthesisConfig, Synthesizer

    best = None
    with Synthesizer(SynthesisConfig(noise="none", seed=seed)) as synth:
        for i in range(frames):
            f = synth.render(i)
            n = int((f.labels == labels.HEAD).sum())
            if best is None or n > best[0]:
                best = (n, synth.builder.primitives())
    return best[1]


def _with_wall(prims, x_m: float = 1.6):
    """`prims` and a 2.4 m wall (a thick box) whose face stands `x_m` right of the camera."""
    from topseg.core.synth.geometry import BOX
    from topseg.core.synth.render import Primitives

    wall = Primitives(
        np.array([BOX], np.int32), np.array([[0.5, 6.0, 1.2]]), np.array([[x_m + 0.5, 0, 1.2]]),
        np.eye(3)[None], np.array([0], np.uint8),
    )  # fmt: skip
    return Primitives.concat([prims, wall])


def _crop_pair(ax, clean, noisy, box, lo, hi, title):
    """Clean | model, the same crop side by side (red: no depth)."""
    v0, v1, u0, u1 = box
    a = colour_depth(clean[v0:v1, u0:u1], lo, hi)
    b = colour_depth(noisy[v0:v1, u0:u1], lo, hi)
    gap = np.full((a.shape[0], 2, 3), 255, np.uint8)
    ax.imshow(np.concatenate([a, gap, b], 1), interpolation="nearest")
    ax.set_title(title, fontsize=9)
    ax.axis("off")


def sensor_figures(plt) -> None:
    """One scene through every sensor, and each ToF / stereo effect beside what it models."""
    from topseg.core import labels
    from topseg.core.camera import TopViewMount
    from topseg.core.sensors import SENSORS, get_sensor
    from topseg.core.synth.noise import StereoNoise, ToFNoise
    from topseg.core.synth.render import raycast

    height = 3000.0
    prims = _with_wall(_scene_primitives())
    rng = np.random.default_rng(0)

    # --- one scene through each sensor -----------------------------------------------------
    fig, axes = plt.subplots(2, len(SENSORS), figsize=(4.2 * len(SENSORS), 7))
    views = {}
    for j, s in enumerate(SENSORS):
        mount = TopViewMount(s.intrinsics, height, sensor=s.name)
        clean, lab = raycast(prims, mount)
        noisy = s.noise().apply(clean, rng, labels=lab)
        views[s.name] = (clean, lab, noisy)
        k = s.intrinsics
        axes[0, j].imshow(colour_depth(clean, 1000, 3200))
        axes[0, j].set_title(f"{s.name}: clean {k.width}x{k.height}, fx {k.fx:g}", fontsize=9)
        axes[1, j].imshow(colour_depth(noisy, 1000, 3200))
        axes[1, j].set_title(f"{s.family.replace('_', ' ')}: {s.noise().spec[:44]}", fontsize=8)
    for ax in axes.ravel():
        ax.axis("off")
    fig.suptitle(f"one scene, camera {height / 1000:g} m above the floor (red: no depth)")
    fig.tight_layout()
    fig.savefig(HERE / "img" / "noise_sensors.png", dpi=60)

    # --- each effect beside what it models ---------------------------------------------------
    tof_s, d435, oak = get_sensor("kinect_v2"), get_sensor("realsense_d435"), get_sensor("oak_d")
    tof = tof_s.noise()
    clean, lab, noisy = views["kinect_v2"]
    fig, axes = plt.subplots(2, 5, figsize=(22, 8.4))
    zz = np.linspace(0.5, 5.0, 50)
    flat = np.full((200, 200), 0, np.uint16)

    # ToF sigma(z): measured on flat floors against Fankhauser et al. 2015 and the Azure spec
    ax = axes[0, 0]
    plain = ToFNoise(speckle=0.0, multipath_mm=0.0, corner_sigma=1.0)
    zs = np.arange(0.75, 5.0, 0.5)
    meas = []
    for z in zs:
        flat[:] = int(z * 1000)
        err = plain.apply(flat, rng)[5:-5, 5:-5].astype(float) - flat[5:-5, 5:-5]
        meas.append(err.std())
    ax.plot(zz, 1.5 - 0.5 * zz + 0.3 * zz**2, "k-", label="Fankhauser 2015: 1.5 - 0.5z + 0.3z^2")
    ax.plot(zs, meas, "o", label="model on a flat floor")
    ax.axhline(17, color="grey", ls=":", label="Azure Kinect spec: sigma <= 17 mm")
    ax.set(xlabel="depth z (m)", ylabel="depth std (mm)", title="ToF: range-dependent noise")
    ax.legend(fontsize=7)

    # ToF flying pixels: a profile across the person's edge
    ax = axes[0, 1]
    person = np.isin(lab, labels.HUMAN_IDS)
    v = int(np.median(np.nonzero(person.any(1))[0]))
    cols = np.nonzero(person[v])[0]
    u0, u1 = max(0, cols.min() - 12), min(clean.shape[1], cols.min() + 12)
    only_fly = ToFNoise(flying=1.0, speckle=0.0, multipath_mm=0.0, sigma_c0_mm=0.0,
                        sigma_c1_mm=0.0, sigma_c2_mm=0.0, flying_px=1)  # fmt: skip
    rows = range(v - 6, v + 7)
    for r in rows:
        out = only_fly.apply(clean, np.random.default_rng(r))
        ax.plot(range(u0, u1), out[r, u0:u1], ".", color="C1", ms=4)
    ax.plot(range(u0, u1), clean[v, u0:u1], "k-", lw=1, label="clean depth (row through the edge)")
    ax.plot([], [], ".", color="C1", label="model, flying=1 (13 rows, noise off)")
    ax.set(xlabel="column", ylabel="depth (mm)", title="ToF: flying (mixed) pixels at the edge")
    ax.legend(fontsize=7)

    # ToF multipath: bias near the floor-wall corner
    ax = axes[0, 2]
    only_mp = ToFNoise(speckle=0.0, flying=0.0, sigma_c0_mm=0.0, sigma_c1_mm=0.0,
                       sigma_c2_mm=0.0)  # fmt: skip
    bias = only_mp.apply(clean, rng).astype(float) - clean
    vm = clean.shape[0] // 2
    face = np.nonzero((lab[vm] == 0) & (clean[vm] < height - 50))[0]
    uc = face.min() if len(face) else clean.shape[1] - 30
    sl = slice(max(0, uc - 25), min(clean.shape[1], uc + 25))
    ax.plot(
        np.arange(clean.shape[1])[sl],
        clean[vm, sl],
        "k-",
        lw=1,
        label="clean: floor, then wall face",
    )
    ax.plot(np.arange(clean.shape[1])[sl], clean[vm, sl] + bias[vm, sl], "C3.-", ms=4,
            label=f"model: + up to {tof.multipath_mm:g} mm in the corner")  # fmt: skip
    ax.set(xlabel="column", ylabel="depth (mm)", title="ToF: multipath at a concave corner")
    ax.invert_yaxis()
    ax.legend(fontsize=7)

    # ToF hair dropout on the head
    head = np.nonzero(lab == labels.HEAD)
    hv, hu = int(np.median(head[0])), int(np.median(head[1]))
    box = (max(0, hv - 26), hv + 26, max(0, hu - 26), hu + 26)
    _crop_pair(axes[0, 3], clean, noisy, box, clean[lab == labels.HEAD].min() - 50, height,
               "ToF: head from above, clean | model (hair dropout)")  # fmt: skip

    # ToF: noise grows towards the corners (less light), invalid border
    ax = axes[0, 4]
    flat = np.full(tof_s.intrinsics.shape, 2500, np.uint16)
    errs = np.stack(
        [tof.apply(flat, np.random.default_rng(i)).astype(float) - 2500 for i in range(6)]
    )
    h, w = flat.shape
    vv, uu = np.indices(flat.shape)
    r2 = (((uu - (w - 1) / 2) / (w / 2)) ** 2 + ((vv - (h - 1) / 2) / (h / 2)) ** 2) / 2
    valid = (errs != -2500).all(0)
    bins = np.linspace(0, 1, 11)
    which = np.digitize(r2, bins)
    sd = [errs[:, (which == b) & valid].std() for b in range(1, 11)]
    ax.plot((bins[1:] + bins[:-1]) / 2, sd, "o", label="model, flat floor at 2.5 m")
    ax.plot(bins, tof.sigma_mm(2.5) * (1 + (tof.corner_sigma - 1) * bins), "k-", lw=1,
            label="sigma(z) (1 + (corner_sigma - 1) r^2)")  # fmt: skip
    ax.set(xlabel="r^2 (0 centre, 1 corners)", ylabel="depth std (mm)",
           title="ToF: noisier towards the corners")  # fmt: skip
    ax.legend(fontsize=7)

    # stereo sigma(z) and steps against Intel's RMS formula
    ax = axes[1, 0]
    for s, c in ((d435, "C0"), (oak, "C2")):
        m = s.noise()
        meas = []
        for z in zs:
            plane = (
                (z * 1000 + 0.3 * (np.arange(400) - 200))[None, :].repeat(200, 0).astype(np.uint16)
            )
            out = StereoNoise(**{**m.to_dict(), "speckle": 0.0, "border_px": 0}).apply(plane, rng)
            ok = out > 0
            meas.append((out[ok].astype(float) - plane[ok]).std())
        ax.plot(zz, 1000 * zz**2 * m.disparity_sigma_px / m.fb, "-", color=c, lw=1,
                label=f"{s.name}: z^2 x {m.disparity_sigma_px:g} px / (f B)")  # fmt: skip
        ax.plot(zs, meas, "o", color=c, label=f"{s.name}: model (1/{m.subpixel} px steps)")
    ax.set(
        xlabel="depth z (m)", ylabel="depth std (mm)", title="stereo: error from disparity noise"
    )
    ax.legend(fontsize=7)

    # stereo invalid band at the left edge
    ax = axes[1, 1]
    for s, c in ((d435, "C0"), (oak, "C2")):
        m = StereoNoise(**{**s.noise().to_dict(), "speckle": 0.0, "disparity_sigma_px": 0.0,
                           "border_px": 0, "min_range_m": 0.1})  # fmt: skip
        widths = []
        for z in zs:
            out = m.apply(np.full((8, 640), int(z * 1000), np.uint16), rng)
            widths.append((out[4] == 0).sum())
        ax.plot(zz, s.baseline_m * s.intrinsics.fx / zz, "-", color=c, lw=1,
                label=f"{s.name}: B f / z (Intel, Luxonis)")  # fmt: skip
        ax.plot(zs, widths, "o", color=c, label=f"{s.name}: model")
    ax.set(
        xlabel="depth z (m)",
        ylabel="band width (px)",
        title="stereo: invalid band at the left edge",
    )
    ax.legend(fontsize=7)

    # stereo edge fattening: share of background pixels reading the foreground's depth
    from scipy import ndimage

    ax = axes[1, 2]
    cl, lb, _ = views["realsense_d435"]
    fg = np.isin(lb, labels.HUMAN_IDS + labels.FURNITURE_IDS)
    dist = ndimage.distance_transform_cdt(~fg, metric="chessboard")
    m = StereoNoise(**{**d435.noise().to_dict(), "speckle": 0.0, "disparity_sigma_px": 0.0})
    share = {r: [] for r in (1, 2, 3)}
    for i in range(4):
        out = m.apply(cl, np.random.default_rng(100 + i)).astype(float)
        bled = (out > 0) & (out < cl - 1000 * m.jump_m)
        for r in share:
            share[r].append(bled[(dist == r) & ~fg].mean())
    rs = np.array(list(share))
    ax.bar(
        rs, [np.mean(share[r]) for r in rs], width=0.5, label="model: background reading foreground"
    )
    ax.plot(
        rs,
        np.where(rs <= m.fatten_px, m.fatten**rs, 0),
        "ko-",
        label="fatten^r up to fatten_px (2)",
    )
    ax.set(xlabel="distance from the foreground r (px)", ylabel="share",
           title="stereo: edge fattening (foreground bleeds 1-2 px)")  # fmt: skip
    ax.set_xticks(rs)
    ax.legend(fontsize=7)

    # stereo speckle holes
    cl, lb, noisy_s = views["realsense_d435"]
    _crop_pair(axes[1, 3], cl, noisy_s, (150, 300, 330, 480), 1000, 3200,
               "stereo (D435): clean | model, speckle holes")  # fmt: skip

    # stereo quantisation: gap between depth levels
    ax = axes[1, 4]
    for s, c in ((d435, "C0"), (oak, "C2")):
        m = s.noise()
        gaps = []
        for z in zs:
            plane = (
                (z * 1000 + 0.3 * (np.arange(400) - 200))[None, :].repeat(200, 0).astype(np.uint16)
            )
            out = m.apply(plane, rng)
            levels = np.unique(out[out > 0])
            gaps.append(np.median(np.diff(levels)))
        ax.plot(zz, 1000 * zz**2 / (m.subpixel * m.fb), "-", color=c, lw=1,
                label=f"{s.name}: z^2 / (2^{m.subpixel_bits} f B)")  # fmt: skip
        ax.plot(zs, gaps, "o", color=c, label=f"{s.name}: model")
    ax.set(xlabel="depth z (m)", ylabel="gap between depth levels (mm)",
           title="stereo: disparity quantisation")  # fmt: skip
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(HERE / "img" / "noise_effects.png", dpi=60)


if __name__ == "__main__":
    main()
