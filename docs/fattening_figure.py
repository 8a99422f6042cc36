"""Draw docs/img/fattening.png: a stereo camera's edge fattening and topseg's thinning of it.

    .venv/bin/python docs/fattening_figure.py

One synthetic scene seen by a RealSense D435 4.5 m above the floor, rendered clean and
through the stereo model with only its edge fattening (no matching noise, no speckle), then
thinned as `inputs.model_input` thins it (`core.fattening`). Left: a crop of a person, clean
| fattened | thinned. Right: around every outline of a person or a piece of furniture, the
share of pixels that read the nearer surface's depth, by signed distance from the true
outline (0 and below: on the nearer surface), over eight draws of the model: clean, fattened,
thinned, and the full model (noise and speckle too) thinned.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def main() -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from noise_figure import _scene_primitives, colour_depth  # docs/, beside this script
    from scipy import ndimage

    from topseg.core import labels
    from topseg.core.camera import TopViewMount
    from topseg.core.fattening import thinning_of, unfatten
    from topseg.core.sensors import get_sensor
    from topseg.core.synth.noise import StereoNoise
    from topseg.core.synth.render import raycast

    sensor = get_sensor("realsense_d435")
    mount = TopViewMount(sensor.intrinsics, 4500.0, sensor=sensor.name)
    clean, lab = raycast(_scene_primitives(), mount)
    full = sensor.noise()
    fatten_only = StereoNoise(**{**full.to_dict(), "speckle": 0.0, "disparity_sigma_px": 0.0})
    radius, jump = thinning_of(mount)

    near = np.isin(lab, labels.HUMAN_IDS + labels.FURNITURE_IDS)
    inside = ndimage.distance_transform_cdt(near, metric="chessboard")
    outside = ndimage.distance_transform_cdt(~near, metric="chessboard")
    signed = np.where(near, 1 - inside, outside)  # 0: the nearer surface's outermost pixel
    rs = np.arange(-3, 4)

    def nearer_share(depth):
        """Per signed distance: the share of pixels with depth reading the nearer surface's
        depth (nearer than the clean depth by more than the jump), or the clean depth where the
        clean pixel is the nearer surface."""
        has = depth > 0
        reads_near = np.where(
            near, np.abs(depth.astype(float) - clean) < jump, depth < clean - jump
        )
        return np.array([reads_near[(signed == r) & has].mean() for r in rs])

    curves = {"clean": nearer_share(clean)}
    draws = {"fattened": [], "fattened, thinned": [], "full model, thinned": []}
    for i in range(8):
        rng = np.random.default_rng(100 + i)
        fat = fatten_only.apply(clean, rng)
        draws["fattened"].append(nearer_share(fat))
        draws["fattened, thinned"].append(nearer_share(unfatten(fat, mount)))
        noisy = full.apply(clean, np.random.default_rng(200 + i))
        draws["full model, thinned"].append(nearer_share(unfatten(noisy, mount)))
        if i == 0:
            example = (fat, unfatten(fat, mount))
    curves.update({k: np.mean(v, 0) for k, v in draws.items()})

    fig, (left, right) = plt.subplots(1, 2, figsize=(13, 4.6), width_ratios=(1.6, 1))
    head = np.argwhere(lab == labels.HEAD)
    (v, u) = head.mean(0).astype(int) if len(head) else np.array(clean.shape) // 2
    v0, u0 = max(v - 35, 0), max(u - 35, 0)
    crops = [clean, *example]
    lo, hi = 2000, 4600
    gap = np.full((70, 2, 3), 255, np.uint8)
    tiles = []
    for d in crops:
        tiles += [colour_depth(d[v0 : v0 + 70, u0 : u0 + 70], lo, hi), gap]
    left.imshow(np.concatenate(tiles[:-1], 1), interpolation="nearest")
    left.set_title(
        f"D435 4.5 m above the floor: clean | fattened (model) | thinned ({radius} px at "
        f"steps > {jump:.0f} mm)",
        fontsize=9,
    )
    left.axis("off")
    for name, style in zip(curves, ("k-o", "C3-o", "C0-o", "C2--s"), strict=True):
        right.plot(rs, curves[name], style, label=name, ms=4)
    right.axvline(0.5, color="grey", lw=0.8)
    right.set(
        xlabel="signed distance from the true outline (px; <= 0 on the nearer surface)",
        ylabel="share reading the nearer surface",
        title="around every outline, 8 draws",
    )
    right.set_xticks(rs)
    right.legend(fontsize=8)
    fig.tight_layout()
    out = HERE / "img" / "fattening.png"
    fig.savefig(out, dpi=60)
    print(f"wrote {out}")
    for name, c in curves.items():
        print(f"{name:22s}", " ".join(f"{x:.3f}" for x in c))


if __name__ == "__main__":
    main()
