"""Plain numpy references of the numba kernels the package ships, for the tests only.

Each reference is written for clarity, not speed: whole-array numpy, every primitive against
every pixel, no culling or early exits. The tests compare the kernels against them bit for
bit (as stumpy keeps its naive versions in one test module).

- `raycast_reference`: `render.raycast` (the ray caster) in numpy.
- `raycast_triangles_reference`: the ray caster with triangles (`render.raycast(prims, mount,
  triangles)`), textbook Moller-Trumbore in the world frame.
- `render_tiny`: pybullet's own TinyRenderer, against which the ray caster was matched.
- `hash_uniform_np`, `kinect_reference`: the Kinect v1 noise model (`noise.KinectNoise`).
- `field_at_reference`, `concavity_reference`, `tof_reference`, `stereo_reference`: the
  time-of-flight and stereo noise models (`noise.ToFNoise`, `noise.StereoNoise`).
- `reference_input`, `model_input_reference`, `model_input_float32_reference`: the forest's
  input (`forest.inputs`).
- `probe_reference`, `extract_reference`, `response_reference`: the depth-difference features.
- `apply_reference`, `predict_reference`, `upsample_reference`, `adaptive_reference`: forest
  inference (`predict.apply`, `predict_proba` at full resolution, on a grid, on an adaptive one);
  `tree_sums_reference`, `trees_walked_reference`: the trees each pixel walks with or without
  the early exit (`_keep_unsure`); `bounded_second_reference`: the lazy grid's bounded second
  posterior (`_summarise_agreed`).
- `SplitMix`, `responses_reference`, `gains_reference`, `best_split_reference`: training's
  per-node random stream, criterion and splitter.
- `reference_settled`, `reference_free`: the real-time CRF's masks (`crf.realtime`).
- `height_map_reference`: the mount's height above the floor (`TopViewMount.height_map_mm`).
- `islands_reference`: blobs too small to be a head or a piece of furniture relabelled,
  and satellite heads beside a larger head (`islands.relabel_islands`), with scipy's
  connected components.
- `upsample_labels_reference`: labels of a decimated frame brought back to the frame's
  resolution by depth (`resolution.upsample_labels`).
- `cell_channels_reference`, `cell_features_reference`: the context check's cells and their
  ring features (`context_check_kernels`), block by block and box by box.
- `tree_ensemble_reference`: the checks' and the prior's boosted trees (`grouped_tree_sums`), walked by
  their links one row at a time.
- `smooth_depth_reference`: the edge-preserving smoothing of noisy depth
  (`denoise.smooth_depth`).
- `thin_edges_reference`: a stereo camera's fattened edges thinned
  (`fattening.thin_edges`).
- `gate_background_reference`: the static cell's background gate
  (`background.gate_background`).
- `vote_surfaces_reference`: robot and object pixels on one continuous surface take its
  majority class (`surfaces.vote_surfaces`), with scipy's connected components of a graph.
- `triangle_distances_reference`, `primitive_distances_reference`: a point's distance to a
  robot's triangle and to its boxes, cylinders, spheres and capsules (`safety.surface`).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage, sparse

from topseg.core import labels
from topseg.core.camera import PAPER_MOUNT, TopViewMount, check_depth, metres_to_mm
from topseg.core.crf.realtime import SETTLED_MARGIN
from topseg.core.forest.tree import Forest
from topseg.core.synth import noise
from topseg.core.synth.geometry import BOX, CAPSULE, CYLINDER, SPHERE
from topseg.core.synth.render import Primitives, Triangles, front_to_back, to_camera

# --- the ray caster (render.raycast) in plain numpy ----------------------------------------


def _np_sphere(o, d, r):
    b = np.einsum("...i,...i->...", o, d)
    c = np.einsum("...i,...i->...", o, o) - r * r
    disc = b * b - c
    with np.errstate(invalid="ignore"):
        t = -b - np.sqrt(disc)
    return np.where((disc >= 0) & (t > 0), t, np.inf)


def _np_side(o, d, r, h):
    a = d[..., 0] ** 2 + d[..., 1] ** 2
    b = o[..., 0] * d[..., 0] + o[..., 1] * d[..., 1]
    c = o[..., 0] ** 2 + o[..., 1] ** 2 - r * r
    disc = b * b - a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (-b - np.sqrt(disc)) / a
        z = o[..., 2] + t * d[..., 2]
    ok = (a >= 1e-14) & (disc >= 0) & (t > 0) & (np.abs(z) <= h)
    return np.where(ok, t, np.inf)


def _np_hit(kind, size, o, d):
    if kind == SPHERE:
        return _np_sphere(o, d, size[0])
    if kind == BOX:
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (-size - o) / d
            t2 = (size - o) / d
        t1 = np.where(np.abs(d) < 1e-12, np.where(np.abs(o) <= size, -np.inf, np.inf), t1)
        t2 = np.where(np.abs(d) < 1e-12, np.where(np.abs(o) <= size, np.inf, -np.inf), t2)
        tn = np.minimum(t1, t2).max(-1)
        tf = np.maximum(t1, t2).min(-1)
        return np.where((tn <= tf) & (tn > 0), tn, np.inf)
    r, h = size[0], size[1]
    best = _np_side(o, d, r, h)
    if kind == CAPSULE:
        for s in (-1.0, 1.0):
            best = np.minimum(best, _np_sphere(o - np.array([0.0, 0.0, s * h]), d, r))
        return best
    for s in (-1.0, 1.0):
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (s * h - o[..., 2]) / d[..., 2]
            x = o[..., 0] + t * d[..., 0]
            y = o[..., 1] + t * d[..., 1]
        ok = (np.abs(d[..., 2]) > 1e-12) & (t > 0) & (x * x + y * y <= r * r)
        best = np.minimum(best, np.where(ok, t, np.inf))
    return best


def raycast_reference(
    prims: Primitives, mount: TopViewMount = PAPER_MOUNT
) -> tuple[np.ndarray, np.ndarray]:
    """The ray caster in plain numpy, every primitive against every pixel (no culling)."""
    k = mount.intrinsics
    prims = front_to_back(prims, mount)  # the same order, so equal depths resolve the same way
    v, u = np.indices(k.shape, dtype=np.float64)
    ray = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones_like(u)], -1)
    norm = np.linalg.norm(ray, axis=-1)
    w = ray / norm[..., None]
    center_c, rot_c = to_camera(prims, mount)
    depth = np.full(k.shape, np.inf)
    lab = np.full(k.shape, labels.NO_DEPTH, np.uint8)
    for i in range(len(prims)):
        o = rot_c[i].T @ (-center_c[i])
        d = w @ rot_c[i]  # R^T w for each pixel
        z = _np_hit(int(prims.kind[i]), prims.size[i], o, d) / norm
        closer = z < depth
        depth[closer] = z[closer]
        lab[closer] = prims.label[i]
    return depth, lab


# --- pybullet's TinyRenderer: the reference the ray caster was matched against ----------------


def camera_matrices(mount: TopViewMount = PAPER_MOUNT, near: float = 0.1, far: float = 10.0):
    """pybullet view and projection matrices equivalent to `mount` (square pixels, centred)."""
    import pybullet as p

    k = mount.intrinsics
    h = mount.height_mm / 1000.0
    if (
        abs(k.cx - (k.width - 1) / 2) > 1e-6
        or abs(k.cy - (k.height - 1) / 2) > 1e-6
        or k.fx != k.fy
    ):
        raise ValueError("pybullet's camera needs a centred principal point and square pixels")
    view = p.computeViewMatrix(
        cameraEyePosition=[0, 0, h], cameraTargetPosition=[0, 0, 0], cameraUpVector=[0, 1, 0]
    )
    fov_y = 2 * np.degrees(np.arctan2(k.height / 2, k.fy))
    proj = list(
        p.computeProjectionMatrixFOV(fov=fov_y, aspect=k.width / k.height, nearVal=near, farVal=far)
    )
    # TinyRenderer samples pixel corners; shift its image half a pixel so it samples pixel
    # centres at (u - cx) / fx like the ray caster and the Kinect model (found by rendering a
    # box with both: with this shift they agree on every pixel)
    proj[8] += 1.0 / k.width
    proj[9] += 1.0 / k.height
    return view, proj


def render_tiny(
    client: int, label_of, mount: TopViewMount = PAPER_MOUNT, near: float = 0.1, far: float = 10.0
):
    """(depth uint16 mm, labels uint8) from pybullet's TinyRenderer.

    `label_of(body_id, link_index)` maps pybullet's segmentation to a label id.
    """
    import pybullet as p

    k = mount.intrinsics
    view, proj = camera_matrices(mount, near, far)
    _, _, _, zbuf, seg = p.getCameraImage(
        k.width, k.height, view, proj, renderer=p.ER_TINY_RENDERER,
        flags=p.ER_SEGMENTATION_MASK_OBJECT_AND_LINKINDEX, physicsClientId=client,
    )  # fmt: skip
    zbuf = np.asarray(zbuf, np.float64).reshape(k.height, k.width)
    seg = np.asarray(seg, np.int64).reshape(k.height, k.width)
    z = far * near / (far - (far - near) * zbuf)
    z[seg < 0] = np.inf
    depth = metres_to_mm(z)
    lab = np.full(k.shape, labels.NO_DEPTH, np.uint8)
    hit = seg >= 0
    body = seg & ((1 << 24) - 1)
    link = (seg >> 24) - 1
    cache: dict[tuple[int, int], int] = {}
    for b, li in set(zip(body[hit].tolist(), link[hit].tolist(), strict=True)):
        cache[(b, li)] = label_of(b, li)
    lut_keys = body * 64 + (link + 1)
    for (b, li), lab_id in cache.items():
        lab[hit & (lut_keys == b * 64 + li + 1)] = lab_id
    lab[depth == 0] = labels.NO_DEPTH
    return depth, lab


def hash_uniform_np(seed: int, index: np.ndarray) -> np.ndarray:
    """`noise._hash_uniform` (splitmix64 of seed + index * golden) in numpy."""
    with np.errstate(over="ignore"):
        z = np.uint64(seed) + index.astype(np.uint64) * noise._GOLDEN
        z = (z ^ (z >> np.uint64(30))) * noise._MIX1
        z = (z ^ (z >> np.uint64(27))) * noise._MIX2
        z = z ^ (z >> np.uint64(31))
    return (z >> np.uint64(11)).astype(np.float64) * (1.0 / 9007199254740992.0)


def kinect_reference(
    model: noise.KinectNoise, depth: np.ndarray, field: np.ndarray, seed: int
) -> np.ndarray:
    """`noise.KinectNoise.apply` in plain numpy, given its draws (slow, whole-array)."""
    depth = check_depth(depth, "noise")
    h, w = depth.shape
    z = depth.astype(np.float64) * 0.001
    valid = depth > 0
    fb = model.fb
    # shadows: projector column against the minimum over everything to the right
    with np.errstate(divide="ignore"):
        up = np.where(valid, np.arange(w)[None, :] - fb / z, np.inf)
    right_min = np.minimum.accumulate(up[:, ::-1], axis=1)[:, ::-1]
    right_min = np.concatenate([right_min[:, 1:], np.full((h, 1), np.inf)], axis=1)
    shadow = valid & (up > right_min + 1e-9)
    jump = np.zeros((h, w), bool)
    for axis in (0, 1):
        a = np.moveaxis(z, axis, 0)
        step = (a[1:] > 0) & (a[:-1] > 0) & (np.abs(a[1:] - a[:-1]) > model.jump_m)
        j = np.zeros(a.shape, bool)
        j[1:] |= step
        j[:-1] |= step
        jump |= np.moveaxis(j, 0, axis)
    jump &= valid
    b = model.edge_band_px

    def near(mask):
        pad = np.pad(mask, b)
        out = np.zeros((h, w), bool)
        for dv in range(2 * b + 1):
            for du in range(2 * b + 1):
                out |= pad[dv : dv + h, du : du + w]
        return out

    near_shadow = near(shadow | ~valid)
    near_jump = near(jump)
    p_drop = np.where(
        near_shadow, model.shadow_dropout, np.where(near_jump, model.edge_dropout, 0.0)
    )
    idx = (np.arange(h * w, dtype=np.uint64).reshape(h, w)) * np.uint64(4)
    r0, r1, r2, r3 = (hash_uniform_np(seed, idx + np.uint64(k)) for k in range(4))
    keep = (
        valid
        & ~shadow
        & ~((p_drop > 0) & (r0 < p_drop))
        & ~((model.speckle > 0) & (r1 < model.speckle))
    )
    with np.errstate(divide="ignore"):
        disp = fb / z
    # flying pixels mix with the neighbour that differs most
    other = depth.astype(np.int64).copy()
    padded = np.pad(depth.astype(np.int64), 1)
    for dv, du in ((0, -1), (0, 1), (-1, 0), (1, 0)):
        n = padded[1 + dv : 1 + dv + h, 1 + du : 1 + du + w]
        better = (n > 0) & (np.abs(n - depth) > np.abs(other - depth))
        other = np.where(better, n, other)
    fly = jump & (r2 < model.flying)
    a = 0.2 + 0.6 * r3
    with np.errstate(divide="ignore"):
        disp = np.where(fly, (1 - a) * disp + a * fb / (other * 0.001), disp)
    c = float(model.noise_cell_px)
    v, u = np.indices((h, w), dtype=np.float64)
    x, y = u / c, v / c
    i0, j0 = x.astype(int), y.astype(int)
    tx, ty = x - i0, y - j0
    w00, w01, w10, w11 = (1 - tx) * (1 - ty), tx * (1 - ty), (1 - tx) * ty, tx * ty
    n = (
        w00 * field[j0, i0]
        + w01 * field[j0, i0 + 1]
        + w10 * field[j0 + 1, i0]
        + w11 * field[j0 + 1, i0 + 1]
    )
    n /= np.sqrt(w00**2 + w01**2 + w10**2 + w11**2)
    disp = disp + model.disparity_sigma_px * n
    disp = np.floor(disp * model.subpixel + 0.5) / model.subpixel
    with np.errstate(divide="ignore", invalid="ignore"):
        zq = fb / disp
    keep &= (disp > 0) & (zq >= model.min_range_m) & (zq <= model.max_range_m)
    out = np.zeros((h, w), np.uint16)
    out[keep] = np.minimum(65535, np.floor(zq[keep] * 1000.0 + 0.5)).astype(np.uint16)
    return out


# --- depth-difference features and forest inference ------------------------------------------


def probe_reference(depth, r, c, inv_d, dr, dc, background, nearest=False):
    """`features.probe`, vectorised: the same float32 arithmetic as the kernel. Off the
    image: the nearest edge pixel when `nearest`, else `background`."""
    pr = r + np.floor(dr * inv_d + np.float32(0.5)).astype(np.int64)
    pc = c + np.floor(dc * inv_d + np.float32(0.5)).astype(np.int64)
    h, w = depth.shape
    if nearest:
        pr, pc = np.clip(pr, 0, h - 1), np.clip(pc, 0, w - 1)
    inside = (pr >= 0) & (pc >= 0) & (pr < h) & (pc < w)
    z = np.full(np.broadcast(pr, pc).shape, background, np.int64)
    z[inside] = depth[pr[inside], pc[inside]]
    z[(z == 0) | (z > background)] = background
    return z


def far_probe_reference(values, r, c, inv_d, dr, dc, background, nearest=False):
    """The v probe of a feature: `probe_reference`, or `background` where the offset is far
    (a component of `features.FAR_OFFSET` or more: off every image by definition)."""
    from topseg.core.forest.features import FAR_OFFSET

    z = probe_reference(values, r, c, inv_d, dr, dc, background, nearest)
    far = (np.abs(dr) >= FAR_OFFSET) | (np.abs(dc) >= FAR_OFFSET)
    return np.where(far, background, z)


def edge_gaps_reference(values):
    """`edge_gaps.fill_edge_gaps` from its definition, with scipy's labelling: the no-depth
    regions (4-connected) with a pixel on the border, filled ring by ring, each pixel the
    least value among its 4-neighbours with depth or filled in an earlier ring. Returns
    (probes, pixels filled)."""
    zero = values == 0
    regions, _ = ndimage.label(zero)  # scipy's default structure: 4-connectivity
    border = np.concatenate([regions[0], regions[-1], regions[:, 0], regions[:, -1]])
    gap = zero & np.isin(regions, border[border > 0])
    out = values.astype(np.int64)
    settled = ~zero
    none = np.iinfo(np.int64).max
    while True:
        least = np.full(values.shape, none, np.int64)
        padded_out = np.pad(np.where(settled, out, none), 1, constant_values=none)
        for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            shifted = padded_out[
                1 + dr : 1 + dr + values.shape[0], 1 + dc : 1 + dc + values.shape[1]
            ]
            least = np.minimum(least, shifted)
        ring = gap & ~settled & (least < none)
        if not ring.any():
            break
        out[ring] = least[ring]
        settled |= ring
    return out.astype(np.uint16), int(np.count_nonzero(gap & settled))


def probe_image_reference(frame):
    """The image a model input's probes read: its `probes` when it has them, else its
    values (a depth frame: the frame)."""
    probes = getattr(frame, "probes", None)
    return probes if probes is not None else reference_input(frame)[0]


def reference_input(frame):
    """(values, scale, floor) of a model input, or of a depth frame's legacy input
    (V = depth, scale = float32(1) / float32(depth), no floor), in plain numpy."""
    if hasattr(frame, "values"):
        return frame.values, frame.scale, frame.floor
    depth = np.asarray(frame)
    with np.errstate(divide="ignore"):
        scale = np.where(depth > 0, np.float32(1.0) / depth.astype(np.float32), np.float32(0))
    return depth, scale.astype(np.float32), np.zeros(depth.shape, bool)


def model_input_reference(depth, mount, features, margin):
    """`inputs.model_input` from first principles, float64: back-project each pixel, rotate
    it into the world (`mount.camera_to_world`), read its height; `margin(depth)` is the
    floor gate's margin. Returns (values, scale, floor, heights)."""
    k = mount.intrinsics
    v, u = np.indices(k.shape, dtype=np.float64)
    z = depth.astype(np.float64)
    cam = np.stack([(u - k.cx) * z / k.fx, (v - k.cy) * z / k.fy, z], axis=-1) / 1000.0
    h = mount.camera_to_world(cam)[..., 2] * 1000.0
    has = depth > 0
    values = np.clip(
        np.floor(features.canonical_height_mm - h + 0.5), 1, features.background_mm - 1
    )
    values = np.where(has, values, 0).astype(np.uint16)
    with np.errstate(divide="ignore"):
        scale = np.where(has, (k.fx / features.reference_focal_px) / z, 0.0)
    floor = has & (np.where(has, h, np.inf) < margin(depth))
    return values, scale, floor, np.where(has, h, np.nan)


def model_input_float32_reference(depth, mount, features, margin):
    """`inputs.model_input` in numpy with the kernel's float32 arithmetic: heights from
    `mount.height_map_mm`; bit-identical, unlike the float64 `model_input_reference`.
    Returns (values, scale, floor)."""
    has = depth > 0
    h = mount.height_map_mm(depth)
    v = np.float32(features.canonical_height_mm) - np.where(has, h, np.float32(0.0))
    top = int(features.background_mm) - 1
    values = np.clip(np.floor(v + np.float32(0.5)), 1, top).astype(np.uint16)
    values[~has] = 0
    with np.errstate(divide="ignore"):
        scale = np.float32(mount.intrinsics.fx / features.reference_focal_px) / depth.astype(
            np.float32
        )
    scale[~has] = 0.0
    floor = has & (np.where(has, h, np.float32(np.inf)) < margin(depth))
    return values, scale, floor


def extract_reference(frame, rows, cols, offsets, background, nearest=False):
    """`features.extract_features`: (n, PC) int16 probe differences at (rows, cols)."""
    _, scale, _ = reference_input(frame)
    values = probe_image_reference(frame)
    inv_d = scale[rows, cols].astype(np.float32)
    r, c, inv = rows[:, None], cols[:, None], inv_d[:, None]
    u_off, v_off = offsets[None, :, :2], offsets[None, :, 2:]
    u = probe_reference(values, r, c, inv, u_off[..., 0], u_off[..., 1], background, nearest)
    v = far_probe_reference(values, r, c, inv, v_off[..., 0], v_off[..., 1], background, nearest)
    return (u - v).astype(np.int16)


def response_reference(frame, offsets, weights, background, nearest=False):
    """One node's response at every pixel with a value (NaN elsewhere), float32 in feature
    order."""
    values, _, _ = reference_input(frame)
    rows, cols = np.nonzero(values)
    f = extract_reference(frame, rows, cols, offsets, background, nearest)
    acc = np.zeros(rows.size, np.float32)
    for j in range(weights.size):  # float32, feature by feature, like the kernel
        acc = acc + weights[j] * f[:, j].astype(np.float32)
    out = np.full(values.shape, np.nan, np.float32)
    out[rows, cols] = acc
    return out


def walked_pixels(frame):
    """(rows, cols) of the pixels the forest walks: a value and not floor, row-major."""
    values, _, floor = reference_input(frame)
    return np.nonzero((values > 0) & ~floor)


def apply_reference(forest: Forest, frame) -> np.ndarray:
    """(T, n) leaf reached by each walked pixel (`walked_pixels`, row-major) in each tree."""
    bg, near = forest.background_mm, forest.nearest_off_image
    _, scale, _ = reference_input(frame)
    values = probe_image_reference(frame)
    rows, cols = walked_pixels(frame)
    inv = scale[rows, cols].astype(np.float32)
    leaves = []
    for root in forest.roots:
        node = np.full(rows.size, root, np.int64)
        while True:
            idx = np.flatnonzero(forest.left[node] >= 0)
            if idx.size == 0:
                break
            nd = node[idx]
            resp = np.zeros(idx.size, np.float32)
            r, c, s = rows[idx], cols[idx], inv[idx]
            for j in range(forest.features_per_node):
                off = forest.offsets[nd, j]
                u = probe_reference(values, r, c, s, off[:, 0], off[:, 1], bg, near)
                v = far_probe_reference(values, r, c, s, off[:, 2], off[:, 3], bg, near)
                resp = resp + forest.weights[nd, j] * (u - v).astype(np.float32)
            node[idx] = forest.left[nd] + np.where(resp < forest.threshold[nd], 0, 1)
        leaves.append(node)
    return np.array(leaves)


def tree_sums_reference(forest: Forest, frame, early_exit=None, early_trees=2):
    """(sums, trees) of each walked pixel (`walked_pixels`): the float32 sum of the leaf
    posteriors of the trees it walks, in tree order, and how many it walks. Every tree when
    `early_exit` is None; else a pixel stops before tree t >= `early_trees` when its best
    class's sum reaches early_exit * t (float32), i.e. its average reaches early_exit."""
    rows, _ = walked_pixels(frame)
    acc = np.zeros((rows.size, forest.posteriors.shape[1]), np.float32)
    trees = np.full(rows.size, forest.n_trees, np.int64)
    for t, node in enumerate(apply_reference(forest, frame)):
        walking = trees == forest.n_trees
        if early_exit is not None and t >= early_trees:
            stop = walking & (acc.max(axis=1) >= np.float32(early_exit) * np.float32(t))
            trees[stop] = t
            walking &= ~stop
        acc[walking] += forest.posteriors[forest.leaf[node[walking]]]
    return acc, trees


def predict_reference(forest: Forest, frame, early_exit=None, early_trees=2) -> np.ndarray:
    """Walk every walked pixel through the trees with numpy (`tree_sums_reference`: every
    tree, or until the early exit), then average over the trees walked (float32, tree
    order); zeros without a value, background with probability 1 on the floor."""
    values, _, floor = reference_input(frame)
    rows, cols = walked_pixels(frame)
    acc, trees = tree_sums_reference(forest, frame, early_exit, early_trees)
    out = np.zeros((*values.shape, forest.posteriors.shape[1]), np.float32)
    out[rows, cols] = acc * (np.float32(1.0) / trees.astype(np.float32))[:, None]
    out[(values > 0) & floor, labels.BACKGROUND] = 1.0
    return out


def trees_walked_reference(forest: Forest, frame, early_exit=None, early_trees=2):
    """(H, W) uint8: how many trees each walked pixel walks (`tree_sums_reference`), 0
    elsewhere."""
    values, _, _ = reference_input(frame)
    rows, cols = walked_pixels(frame)
    out = np.zeros(values.shape, np.uint8)
    out[rows, cols] = tree_sums_reference(forest, frame, early_exit, early_trees)[1]
    return out


def upsample_reference(grid_proba, values, floor, stride, sigma_mm) -> np.ndarray:
    """`predict._upsample` in numpy (float64): each pixel between grid points averages the
    posteriors of its (up to four) surrounding grid pixels with a value, weighted by
    (s - |dr|)(s - |dc|) exp(-((v_grid - v) / sigma)^2); the nearest in value where every
    weight underflows. Grid pixels keep `grid_proba`; zeros without a value, background on
    the floor."""
    h, w = values.shape
    out = np.zeros(grid_proba.shape, np.float64)
    last_r, last_c = (h - 1) - (h - 1) % stride, (w - 1) - (w - 1) % stride
    for r in range(h):
        for c in range(w):
            r0, c0 = r - r % stride, c - c % stride
            if r == r0 and c == c0:
                out[r, c] = grid_proba[r, c]
                continue
            if values[r, c] == 0:
                continue
            if floor[r, c]:
                out[r, c, labels.BACKGROUND] = 1.0
                continue
            grid = {
                (gr, gc)
                for gr in (r0, min(r0 + stride, last_r))
                for gc in (c0, min(c0 + stride, last_c))
            }
            grid = [g for g in sorted(grid) if values[g] > 0]
            weights = np.array(
                [
                    (stride - abs(r - gr))
                    * (stride - abs(c - gc))
                    * np.exp(-(((float(values[gr, gc]) - float(values[r, c])) / sigma_mm) ** 2))
                    for gr, gc in grid
                ]
            )
            if weights.sum() > 1e-30:
                out[r, c] = sum(wt * grid_proba[g] for wt, g in zip(weights, grid, strict=True))
                out[r, c] /= weights.sum()
            elif grid:
                near = min(grid, key=lambda g: abs(float(values[g]) - float(values[r, c])))
                out[r, c] = grid_proba[near]
    return out


def bounded_second_reference(summary, values, floor, stride, sigma_mm) -> np.ndarray:
    """`predict._summarise_agreed` in numpy (float64): (H, W) the second posterior a lazy
    upsampling stores at each in-between pixel with a value, off the floor, whose weighing
    grid corners (float32 weight > 0, as `upsample_reference` weighs them, summing to more
    than 1e-30) share one argmax in `summary`: the weighted mean of their second posteriors, where it stays below the
    weighted mean of their top ones. NaN at every other pixel (its exact summary stands)."""
    amax, pmax, psecond = summary
    h, w = values.shape
    out = np.full((h, w), np.nan)
    last_r, last_c = (h - 1) - (h - 1) % stride, (w - 1) - (w - 1) % stride
    for r in range(h):
        for c in range(w):
            r0, c0 = r - r % stride, c - c % stride
            if (r == r0 and c == c0) or values[r, c] == 0 or floor[r, c]:
                continue
            corners = {
                (gr, gc)
                for gr in (r0, min(r0 + stride, last_r))
                for gc in (c0, min(c0 + stride, last_c))
            }
            weighed = []
            for gr, gc in sorted(corners):
                if values[gr, gc] == 0:
                    continue
                dv = (float(values[gr, gc]) - float(values[r, c])) / sigma_mm
                wt = (stride - abs(r - gr)) * (stride - abs(c - gc)) * np.float32(np.exp(-dv * dv))
                if wt > 0:
                    weighed.append((wt, (gr, gc)))
            total = sum(wt for wt, _ in weighed)
            if total <= 1e-30 or len({int(amax[g]) for _, g in weighed}) != 1:
                continue  # underflowed: `_between` takes the nearest corner, exactly
            top = sum(wt * float(pmax[g]) for wt, g in weighed) / total
            second = sum(wt * float(psecond[g]) for wt, g in weighed) / total
            if second < top:
                out[r, c] = second
    return out


def adaptive_reference(
    forest: Forest, frame, stride, levels, confidence, reach_mm, sigma_mm, early_exit=None
):
    """`predict_proba(..., stride, adaptive=levels, early_exit=)` in numpy: (posteriors,
    walked).

    Every pixel's exact posterior comes from `predict_reference` (with `early_exit`). The
    grid stride * 2**levels keeps them; each finer grid, down to `stride`, keeps them at its
    pixels between the coarser grid's points unless that grid settles the pixel: all of its
    up-to-four surrounding coarser points have a value within `reach_mm` of the pixel's and the same
    argmax with posterior >= `confidence`; a settled pixel takes the coarser grid's
    `upsample_reference` posterior. The finest grid is then upsampled to every pixel.
    `walked` (uint8) holds the trees walked (`trees_walked_reference`) at the grid pixels that
    kept their exact posterior (value, not floor), 0 elsewhere."""
    values, _, floor = reference_input(frame)
    exact = predict_reference(forest, frame, early_exit).astype(np.float64)
    trees = trees_walked_reference(forest, frame, early_exit)
    h, w = values.shape
    walkable = (values > 0) & ~floor
    s = stride << levels
    grid = np.zeros_like(exact)
    grid[::s, ::s] = exact[::s, ::s]
    walked = np.zeros(values.shape, np.uint8)
    walked[::s, ::s] = trees[::s, ::s]
    while s > stride:
        coarse, s = s, s // 2
        between = upsample_reference(grid, values, floor, coarse, sigma_mm)
        last_r, last_c = (h - 1) - (h - 1) % coarse, (w - 1) - (w - 1) % coarse
        for r in range(0, h, s):
            for c in range(0, w, s):
                if r % coarse == 0 and c % coarse == 0:
                    continue  # a point of the coarser grid
                if not walkable[r, c]:
                    grid[r, c] = exact[r, c]  # zeros without a value, background on the floor
                    continue
                r0, c0 = r - r % coarse, c - c % coarse
                corners = [
                    (gr, gc)
                    for gr in (r0, min(r0 + coarse, last_r))
                    for gc in (c0, min(c0 + coarse, last_c))
                ]
                labels_ = {int(np.argmax(grid[g])) for g in corners}
                settled = (
                    len(labels_) == 1
                    and all(values[g] > 0 for g in corners)
                    and all(abs(int(values[g]) - int(values[r, c])) < reach_mm for g in corners)
                    and all(grid[g].max() >= confidence for g in corners)
                )
                grid[r, c] = between[r, c] if settled else exact[r, c]
                walked[r, c] = 0 if settled else trees[r, c]
    if stride > 1:
        return upsample_reference(grid, values, floor, stride, sigma_mm), walked
    return grid, walked


# --- forest training: the node stream, the criterion, the splitter ---------------------------

MASK = (1 << 64) - 1
GOLDEN = 0x9E3779B97F4A7C15


class SplitMix:
    """Python reference of the per-node splitmix64 stream."""

    def __init__(self, key, node_id):
        self.state = (key + node_id * GOLDEN) & MASK
        self.state = self.next()

    def next(self):
        self.state = (self.state + GOLDEN) & MASK
        z = self.state
        z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & MASK
        z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & MASK
        return z ^ (z >> 31)

    def uniform(self):
        return (self.next() >> 11) * (1.0 / 9007199254740992.0)

    def randint(self, n):
        return int(self.uniform() * n)

    def unit_vector(self, k):
        while True:
            v = np.array([2.0 * self.uniform() - 1.0 for _ in range(k)])
            sq = 0.0
            for x in v:
                sq += x * x
            if 0.0 < sq <= 1.0:
                return v / np.sqrt(sq)


def responses_reference(fm, ids, feats, weights):
    """`splitter._responses`: the weighted sum of features in float32, feature by feature."""
    acc = np.zeros(len(ids), np.float32)
    for j in range(len(feats)):
        acc = acc + weights[j] * fm[feats[j], ids].astype(np.float32)
    return acc


def entropy_bits(counts):
    """Shannon entropy (bits) of class counts."""
    n = counts.sum()
    p = counts[counts > 0] / n
    return float(-(p * np.log2(p)).sum())


def gains_reference(resp, y, thresholds, n_classes):
    """Information gain of each threshold by brute force: split, count, entropies."""
    parent = np.bincount(y, minlength=n_classes)
    h = entropy_bits(parent)
    out = []
    for t in thresholds:
        go_left = resp < t
        left = np.bincount(y[go_left], minlength=n_classes)
        right = parent - left
        n_l, n_r = left.sum(), right.sum()
        child = (n_l * entropy_bits(left) if n_l else 0) + (n_r * entropy_bits(right) if n_r else 0)
        out.append(h - child / len(y))
    return np.array(out)


def best_split_reference(fm, y, ids, key, node_id, n_cand, n_thr, k, linear, cap):
    """The node optimisation written plainly, with the same stream of draws."""
    rng = SplitMix(key, node_id)
    n = len(ids)
    sub = np.array([ids[rng.randint(n)] for _ in range(cap)]) if n > cap else ids
    m = len(sub)
    ys = y[sub]
    best = (-1.0, None, None, None)
    for _ in range(n_cand):
        feats = np.array([rng.randint(fm.shape[0]) for _ in range(k)])
        weights = rng.unit_vector(k).astype(np.float32) if linear else np.ones(k, np.float32)
        resp = responses_reference(fm, sub, feats, weights)
        thr = np.sort(np.array([resp[rng.randint(m)] for _ in range(min(n_thr, m))]))
        gains = gains_reference(resp, ys, thr, labels.NUM_CLASSES)
        for g, t in zip(gains, thr, strict=True):
            if g > best[0] + 1e-12:
                best = (g, feats, weights, t)
    return best


# --- the real-time CRF's masks -----------------------------------------------------------------


def edge_weights_reference(depth, config):
    """`crf.energy.edge_weights` in plain numpy, the reference its numba kernel must match."""
    d = np.asarray(depth).astype(np.float32)
    valid = d > 0
    wh = np.full((d.shape[0], d.shape[1] - 1), config.smoothness, np.float32)
    wv = np.full((d.shape[0] - 1, d.shape[1]), config.smoothness, np.float32)
    if config.depth_sigma_mm > 0:
        k = np.float32(-0.5 / config.depth_sigma_mm**2)
        wh *= np.exp(k * (d[:, 1:] - d[:, :-1]) ** 2)
        wv *= np.exp(k * (d[1:, :] - d[:-1, :]) ** 2)
    wh[~(valid[:, 1:] & valid[:, :-1])] = 0.0
    wv[~(valid[1:, :] & valid[:-1, :])] = 0.0
    return wh, wv


def reference_settled(proba, valid, smoothness, eps, margin=SETTLED_MARGIN):
    """Argmax ahead of every other label by more than any pixel's edges weigh (+ margin)."""
    top2 = np.sort(np.maximum(proba.astype(np.float64), eps), axis=2)[..., -2:]
    return valid & (np.log(top2[..., 1]) - np.log(top2[..., 0]) >= 4 * smoothness + margin)


def reference_free(amax, pmax, valid, confidence, ring, settled):
    """Neither sure (confident, every 4-neighbour with depth agrees) nor settled; + ring."""
    h, w = amax.shape
    pad_a = np.pad(amax.astype(np.int64), 1, constant_values=-1)
    pad_v = np.pad(valid, 1, constant_values=False)
    agree = np.ones((h, w), bool)
    for di, dj in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        na = pad_a[1 + di : 1 + di + h, 1 + dj : 1 + dj + w]
        nv = pad_v[1 + di : 1 + di + h, 1 + dj : 1 + dj + w]
        agree &= ~nv | (na == amax)
    free = valid & ~((pmax >= confidence) & agree) & ~settled
    for _ in range(ring):
        free = (
            ndimage.binary_dilation(free, ndimage.generate_binary_structure(2, 1))
            & valid
            & ~settled
        )
    return free


def band_problem_reference(proba, amax, index, wh, wv, eps, scale):
    """`crf.realtime.band_problem` in numpy: (pix, unary, nbr, nw, init) of the band pixels
    (index >= 0, numbered row-major). The logs are float32 as in the kernel, but numpy's
    float32 log may differ from libm's in the last place: unaries can differ by 1 where
    -log(p) * scale lies within rounding of a half."""
    h, w = amax.shape
    c = proba.shape[2]
    pix = np.flatnonzero(index.ravel() >= 0)
    rows, cols = np.divmod(pix, w)
    p = proba[rows, cols].astype(np.float32)
    logs = (-np.log(np.maximum(p, np.float32(1e-30)))).astype(np.float64) * scale
    cap = np.int32(np.rint(-np.log(np.float32(eps)).astype(np.float64) * scale))
    unary = np.where(p <= eps, cap, np.rint(logs)).astype(np.int64)
    nbr = np.full((pix.size, 4), -1, np.int64)
    nw = np.zeros((pix.size, 4), np.int64)
    wpad_h = np.zeros((h, w + 1), np.float64)  # wpad_h[i, j]: the edge left of (i, j)
    wpad_h[:, 1:w] = wh
    wpad_v = np.zeros((h + 1, w), np.float64)  # wpad_v[i, j]: the edge above (i, j)
    wpad_v[1:h, :] = wv
    steps = (
        (0, -1, wpad_h[rows, cols]),
        (0, 1, wpad_h[rows, cols + 1]),
        (-1, 0, wpad_v[rows, cols]),
        (1, 0, wpad_v[rows + 1, cols]),
    )
    for s, (di, dj, weight) in enumerate(steps):
        iw = np.rint(weight * scale).astype(np.int64)
        has = iw > 0
        ni = np.clip(rows + di, 0, h - 1)
        nj = np.clip(cols + dj, 0, w - 1)
        q = index[ni, nj]
        band = has & (q >= 0)
        nbr[band, s], nw[band, s] = q[band], iw[band]
        fixed = has & (q < 0)
        other = np.arange(c)[None, :] != amax[ni, nj][:, None]
        unary += np.where(fixed[:, None] & other, iw[:, None], 0)
    return pix, unary, nbr, nw, amax.ravel()[pix].astype(np.int64)


# --- the time-of-flight and stereo noise models (noise.ToFNoise, noise.StereoNoise) ------------


def _shift0(a: np.ndarray, dv: int, du: int) -> np.ndarray:
    """out[v, u] = a[v + dv, u + du], 0 outside the frame."""
    h, w = a.shape
    pad = max(abs(dv), abs(du))
    p = np.pad(a, pad)
    return p[pad + dv : pad + dv + h, pad + du : pad + du + w]


def field_at_reference(field: np.ndarray, cell: float, shape: tuple[int, int]) -> np.ndarray:
    """`noise._field_at` at every pixel: the coarse normal field, bilinear and renormalised."""
    v, u = np.indices(shape, dtype=np.float64)
    x, y = u / cell, v / cell
    i0, j0 = x.astype(int), y.astype(int)
    tx, ty = x - i0, y - j0
    w00, w01, w10, w11 = (1 - tx) * (1 - ty), tx * (1 - ty), (1 - tx) * ty, tx * ty
    n = (
        w00 * field[j0, i0]
        + w01 * field[j0, i0 + 1]
        + w10 * field[j0 + 1, i0]
        + w11 * field[j0 + 1, i0 + 1]
    )
    return n / np.sqrt(w00 * w00 + w01 * w01 + w10 * w10 + w11 * w11)


def concavity_reference(depth: np.ndarray, s: int, jump_mm: float) -> np.ndarray:
    """`noise._concavity` at every pixel: max over rows and columns of d0/d(-s) + d0/d(+s) - 2
    where the 2s+1 segment has depth throughout and no neighbour step above `jump_mm`."""
    d = depth.astype(np.int64)
    best = np.zeros(d.shape)
    for dv, du in ((1, 0), (0, 1)):
        seg = [_shift0(d, k * dv, k * du) for k in range(-s, s + 1)]
        ok = np.all([a != 0 for a in seg], axis=0)
        for k in range(len(seg) - 1):
            ok &= np.abs(seg[k] - seg[k + 1]) <= jump_mm
        with np.errstate(divide="ignore", invalid="ignore"):
            c = d.astype(np.float64) / seg[0] + d.astype(np.float64) / seg[-1] - 2.0
        best = np.where(ok & (c > best), c, best)
    return best


def tof_reference(
    model: noise.ToFNoise,
    depth: np.ndarray,
    dark: np.ndarray,
    gauss: np.ndarray,
    dark_field: np.ndarray,
    seed: int,
    fov: float,
) -> np.ndarray:
    """`noise.ToFNoise.run` in plain numpy, given its draws (whole-array)."""
    depth = check_depth(depth, "noise")
    h, w = depth.shape
    d = depth.astype(np.int64)
    idx = np.arange(h * w, dtype=np.uint64).reshape(h, w) * np.uint64(4)
    r0, r1, r2, r3 = (hash_uniform_np(seed, idx + np.uint64(k)) for k in range(4))
    v, u = np.indices((h, w))
    keep = depth > 0
    b = model.border_px
    keep &= (u >= b) & (v >= b) & (u < w - b) & (v < h - b)
    rx = (u - (w - 1) / 2.0) / (w / 2.0)
    ry = (v - (h - 1) / 2.0) / (h / 2.0)
    rr = (rx * rx + ry * ry) / 2.0
    du, dv = u - (w - 1) / 2.0, v - (h - 1) / 2.0
    keep &= du * du + dv * dv <= fov * fov * (w * w + h * h) / 4.0  # inside the valid circle
    is_dark = dark != 0
    thr = noise._normal_quantile(model.dark_dropout)
    keep &= ~(is_dark & (field_at_reference(dark_field, float(model.dark_cell_px), (h, w)) < thr))
    if model.speckle > 0:
        keep &= ~(r3 < model.speckle)
    z = depth * 0.001
    # the mixed-pixel band
    lo, hi = d.copy(), d.copy()
    k = model.flying_px
    for dv in range(-k, k + 1):
        for du in range(-k, k + 1):
            n = _shift0(d, dv, du)
            lo = np.where((n > 0) & (n < lo), n, lo)
            hi = np.where((n > 0) & (n > hi), n, hi)
    jump_mm = 1000.0 * model.jump_m
    band = (hi - lo) > jump_mm
    if model.edge_invalid > 0:
        keep &= ~(band & (r0 < model.edge_invalid))
    fly = band & (r1 < model.flying)
    a = 0.2 + 0.6 * r2
    z = np.where(fly, (lo + a * (hi - lo)) * 0.001, z)
    if model.multipath_mm > 0:
        c = concavity_reference(depth, model.multipath_px, jump_mm)
        f = np.minimum(1.0, (c - model.concave_min) / (model.concave_full - model.concave_min))
        z = np.where(c > model.concave_min, z + 0.001 * model.multipath_mm * f, z)
    c0, c1, c2 = model.sigma_c0_mm, model.sigma_c1_mm, model.sigma_c2_mm
    sigma = (c0 + c1 * z + c2 * z * z) * (1.0 + (model.corner_sigma - 1.0) * rr)
    sigma = np.where(is_dark, sigma * model.dark_sigma, sigma)
    z = z + 0.001 * sigma * gauss
    keep &= (z >= model.min_range_m) & (z <= model.max_range_m)
    out = metres_to_mm(np.where(keep, z, 0.0))
    out[~keep] = 0
    return out


def stereo_reference(
    model: noise.StereoNoise,
    depth: np.ndarray,
    field: np.ndarray,
    speckle_field: np.ndarray,
    seed: int,
) -> np.ndarray:
    """`noise.StereoNoise.run` in plain numpy, given its draws (whole-array)."""
    depth = check_depth(depth, "noise")
    h, w = depth.shape
    d = depth.astype(np.int64)
    valid = depth > 0
    fb = model.fb
    # occlusion in the second imager: as the Kinect's projector shadow
    z0 = depth.astype(np.float64) * 0.001
    with np.errstate(divide="ignore"):
        up = np.where(valid, np.arange(w)[None, :] - fb / z0, np.inf)
    right_min = np.minimum.accumulate(up[:, ::-1], axis=1)[:, ::-1]
    right_min = np.concatenate([right_min[:, 1:], np.full((h, 1), np.inf)], axis=1)
    occluded = valid & (up > right_min + 1e-9)
    idx = np.arange(h * w, dtype=np.uint64).reshape(h, w) * np.uint64(4)
    r0 = hash_uniform_np(seed, idx)
    v, u = np.indices((h, w))
    keep = valid.copy()
    b = model.border_px
    keep &= (u >= b) & (v >= b) & (u < w - b) & (v < h - b)
    # edge fattening: the first ring with a nearer surface decides
    src = d.copy()
    fattened = np.zeros((h, w), bool)
    decided = np.zeros((h, w), bool)
    jump_mm = 1000.0 * model.jump_m
    for r in range(1, model.fatten_px + 1):
        m = np.zeros((h, w), np.int64)
        for dv in range(-r, r + 1):
            for du in range(-r, r + 1):
                if max(abs(dv), abs(du)) != r:
                    continue
                n = _shift0(d, dv, du)
                m = np.where((n > 0) & ((m == 0) | (n < m)), n, m)
        here = ~decided & (m > 0) & (d - m > jump_mm)
        take = here & (r0 < model.fatten**r)
        src = np.where(take, m, src)
        fattened |= take
        decided |= here
    keep &= ~(occluded & ~fattened)
    with np.errstate(divide="ignore"):
        disp = fb / (src * 0.001)
    keep &= ~(u < disp)
    thr = noise._normal_quantile(model.speckle)
    shape = (h, w)
    keep &= ~(field_at_reference(speckle_field, float(model.speckle_cell_px), shape) < thr)
    disp = disp + model.disparity_sigma_px * field_at_reference(
        field, float(model.noise_cell_px), shape
    )
    disp = np.floor(disp * model.subpixel + 0.5) / model.subpixel
    keep &= disp > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        z = fb / disp
    keep &= (z >= model.min_range_m) & (z <= model.max_range_m)
    out = metres_to_mm(np.where(keep, z, 0.0))
    out[~keep] = 0
    return out


# --- the mount's height map (camera.TopViewMount.height_map_mm) -----------------------------


def height_map_reference(depth: np.ndarray, mount: TopViewMount) -> np.ndarray:
    """Height above the floor (mm, float64, NaN without depth), from scipy's rotations.

    World up in camera coordinates is R @ (0, 0, 1) with R = Rx(pitch) Ry(roll) diag(1,-1,-1);
    a pixel's height is the camera's height plus up . X for its back-projected point X (mm).
    """
    from scipy.spatial.transform import Rotation

    from topseg.core.camera import backproject

    tilt = Rotation.from_euler("XY", [mount.pitch_deg, mount.roll_deg], degrees=True)
    r = tilt.as_matrix() @ np.diag([1.0, -1.0, -1.0])
    up = r @ np.array([0.0, 0.0, 1.0])
    x_mm = backproject(depth, mount.intrinsics).astype(np.float64) * 1000.0
    return mount.height_mm + x_mm @ up


# --- the ray caster for a tilted camera, in the world frame (render.raycast) ------------------


def raycast_world_reference(
    prims: Primitives, mount: TopViewMount
) -> tuple[np.ndarray, np.ndarray]:
    """The ray caster cast in the world frame: each pixel's ray leaves the camera centre along
    the world direction of ((u - cx) / fx, (v - cy) / fy, 1), turned by scipy's rotation of
    (pitch, roll); depth = distance along the ray x the cosine to the optical axis. Shares no
    code with `render.to_camera`, so it checks the tilt independently."""
    from scipy.spatial.transform import Rotation

    k = mount.intrinsics
    tilt = Rotation.from_euler("XY", [mount.pitch_deg, mount.roll_deg], degrees=True)
    r = tilt.as_matrix() @ np.diag([1.0, -1.0, -1.0])  # world -> camera
    centre = np.array([0.0, 0.0, mount.height_mm / 1000.0])
    prims = front_to_back(prims, mount)
    v, u = np.indices(k.shape, dtype=np.float64)
    ray = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones_like(u)], -1)
    norm = np.linalg.norm(ray, axis=-1)
    w_world = (ray / norm[..., None]) @ r  # R^T w per pixel
    depth = np.full(k.shape, np.inf)
    lab = np.full(k.shape, labels.NO_DEPTH, np.uint8)
    for i in range(len(prims)):
        rot = prims.rot[i]
        o = rot.T @ (centre - prims.center[i])
        d = w_world @ rot
        z = _np_hit(int(prims.kind[i]), prims.size[i], o, d) / norm
        closer = z < depth
        depth[closer] = z[closer]
        lab[closer] = prims.label[i]
    return depth, lab


def raycast_triangles_reference(
    prims: Primitives, triangles: Triangles, mount: TopViewMount
) -> tuple[np.ndarray, np.ndarray]:
    """The ray caster over primitives and triangles: the primitives as
    `raycast_world_reference` casts them, then every triangle against every pixel by textbook
    Moller-Trumbore (two-sided) in the world frame, along the world direction of
    ((u - cx) / fx, (v - cy) / fy, 1) so the distance along it is the depth; a triangle takes a
    pixel only when strictly nearer."""
    from scipy.spatial.transform import Rotation

    k = mount.intrinsics
    depth, lab = raycast_world_reference(prims, mount)
    tilt = Rotation.from_euler("XY", [mount.pitch_deg, mount.roll_deg], degrees=True)
    r = tilt.as_matrix() @ np.diag([1.0, -1.0, -1.0])  # world -> camera
    origin = np.array([0.0, 0.0, mount.height_mm / 1000.0])
    v, u = np.indices(k.shape, dtype=np.float64)
    ray = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones_like(u)], -1)
    d = ray @ r  # R^T ray per pixel
    for tri, tri_label in zip(triangles.vertices, triangles.label, strict=True):
        e1, e2 = tri[1] - tri[0], tri[2] - tri[0]
        p = np.cross(d, e2)
        det = p @ e1
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            s = origin - tri[0]
            bu = (p @ s) * inv
            q = np.cross(s, e1)
            bv = (d @ q) * inv
            t = (e2 @ q) * inv
        hit = (det != 0) & (bu >= 0) & (bu <= 1) & (bv >= 0) & (bu + bv <= 1) & (t > 0)
        closer = hit & (t < depth)
        depth[closer] = t[closer]
        lab[closer] = tri_label
    return depth, lab


def islands_reference(
    labels, depth, k, min_area_cm2, no_depth, satellite_head_cm2=0.0, radius_cm=40.0, head=1,
    edge_px=0, edge_share=None,
):  # fmt: skip
    """(labels after, small blobs relabelled per class, satellite heads relabelled), every
    blob judged on the labels as given; a relabelled blob takes the label most often found
    across its border (one vote per blob pixel - outside pixel 4-neighbour pair, the outside
    pixel neither its class nor no-depth; ties to the lower id; none: it keeps its class):
    - every 4-connected blob of a class c whose area (the sum of (z / fx) (z / fy) over its
      pixels) is under `min_area_cm2[c]` (0: none), or under `edge_share[c]` of it for a
      blob with a pixel within `edge_px` of the image's edge;
    - every other `head` blob under `satellite_head_cm2` whose mean position ((u - cx) z / fx,
      (v - cy) z / fy) lies within `radius_cm` of a larger head blob's."""
    num_classes = len(min_area_cm2)
    out = np.array(labels, copy=True)
    z = np.asarray(depth, np.float64)
    v, u = np.indices(z.shape)
    x_mm, y_mm = (u - k.cx) * z / k.fx, (v - k.cy) * z / k.fy
    area_cm2 = z**2 / (k.fx * k.fy) / 100.0
    relabelled = np.zeros(num_classes, np.int64)
    heads = []  # (area, x, y, mask) of head blobs not small
    near_edge = np.zeros(z.shape, bool)
    if edge_px > 0:
        near_edge[:edge_px], near_edge[-edge_px:] = True, True
        near_edge[:, :edge_px], near_edge[:, -edge_px:] = True, True

    def border_label(inside, c):
        votes = np.zeros(num_classes, np.int64)
        for dv, du in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            # pairs (p in the blob, q = p + (dv, du)): q's label, where q is outside
            src = _shift0(inside.astype(np.uint8), dv, du).astype(bool)
            q_labels = labels[src]
            keep = (q_labels != c) & (q_labels != no_depth) & (q_labels < num_classes)
            votes += np.bincount(q_labels[keep].astype(np.int64), minlength=num_classes)
        return None if votes.max() == 0 else int(np.argmax(votes))

    for c in range(num_classes):
        if not (min_area_cm2[c] > 0 or (c == head and satellite_head_cm2 > 0)):
            continue
        blobs, n = ndimage.label(labels == c)  # scipy's default structure: 4-connectivity
        for b in range(1, n + 1):
            inside = blobs == b
            area = area_cm2[inside].sum()
            share = 1.0 if edge_share is None or not near_edge[inside].any() else edge_share[c]
            if area >= min_area_cm2[c] * share:
                if c == head:
                    heads.append((area, x_mm[inside].mean(), y_mm[inside].mean(), inside))
                continue
            label = border_label(inside, c)
            if label is not None:
                out[inside] = label
                relabelled[c] += 1
    satellites = 0
    for area, x, y, inside in heads:
        if area >= satellite_head_cm2:
            continue
        near = [a > area and np.hypot(x - ax, y - ay) < 10.0 * radius_cm for a, ax, ay, _ in heads]
        label = border_label(inside, head)
        if any(near) and label is not None:
            out[inside] = label
            satellites += 1
    return out, relabelled, satellites


def upsample_labels_reference(depth, small_labels, small_depth, factor):
    """`resolution.upsample_labels` in numpy: the four candidates of every pixel as whole
    arrays, the first nearest in depth among those with a label (argmin keeps the first)."""
    h, w = depth.shape
    sh, sw = small_labels.shape
    r = np.arange(h)
    c = np.arange(w)
    i0 = r // factor
    i1 = np.minimum(i0 + (r % factor != 0), sh - 1)
    j0 = c // factor
    j1 = np.minimum(j0 + (c % factor != 0), sw - 1)
    rows = [i0, i0, i1, i1]
    cols = [j0, j1, j0, j1]
    d = depth.astype(np.int64)
    gaps, labs = [], []
    for ri, ci in zip(rows, cols, strict=True):
        s = small_depth[np.ix_(ri, ci)].astype(np.int64)
        lab = small_labels[np.ix_(ri, ci)]
        usable = (s != 0) & (lab != labels.NO_DEPTH)
        gaps.append(np.where(usable, np.abs(s - d), np.iinfo(np.int64).max))
        labs.append(lab)
    gaps = np.stack(gaps)
    best = np.argmin(gaps, axis=0)
    out = np.take_along_axis(np.stack(labs), best[None], axis=0)[0].astype(np.uint8)
    out[np.min(gaps, axis=0) == np.iinfo(np.int64).max] = labels.BACKGROUND
    out[depth == 0] = labels.NO_DEPTH
    return out


def smooth_depth_reference(depth, edge_mm, alpha, iterations):
    """`denoise.smooth_depth` in plain Python over numpy arrays, float32 as the kernels: each
    iteration smooths every row left to right and right to left, then every column top down
    and bottom up; a pixel becomes alpha * own + (1 - alpha) * its smoothed predecessor when
    both have depth and differ by less than edge_mm[own raw depth]."""
    x = depth.astype(np.float32)
    a = np.float32(alpha)
    b = np.float32(1.0) - a

    def sweep(line, raw):
        for order in (range(1, len(line)), range(len(line) - 2, -1, -1)):
            step = 1 if order.step == 1 else -1
            for i in order:
                prev, v = line[i - step], line[i]
                if prev > 0 and v > 0 and abs(v - prev) < edge_mm[raw[i]]:
                    line[i] = a * v + b * prev

    for _ in range(iterations):
        for r in range(x.shape[0]):
            sweep(x[r], depth[r])
        for c in range(x.shape[1]):
            col = x[:, c].copy()
            sweep(col, depth[:, c])
            x[:, c] = col
    out = np.clip(np.floor(x + np.float32(0.5)), 1, 65535).astype(np.uint16)
    out[depth == 0] = 0
    return out


def fill_holes_reference(
    depth: np.ndarray, max_sum_z2: float, span_mm: float, surface_share: float = 1.0
) -> tuple[np.ndarray, int]:
    """`holes._fill_holes` in plain numpy: every 4-connected region without depth with at
    least `surface_share` of its border (each hole-pixel / depth-pixel 4-neighbour pair
    once) within `span_mm` of the border's nearest depth, and whose pixel count times the
    mean of those near border depths squared is at most `max_sum_z2`, takes that mean,
    rounded half up."""
    d = depth.astype(np.int64)
    h, w = d.shape
    holes, n = ndimage.label(d == 0)
    out = depth.copy()
    pairs = []  # (hole id, the neighbour's depth) of every border pair
    for dv, du in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        nb = np.zeros_like(d)  # the neighbour's depth, 0 off the image
        nb[max(0, -dv) : h - max(0, dv), max(0, -du) : w - max(0, du)] = d[
            max(0, dv) : h + min(0, dv) or None, max(0, du) : w + min(0, du) or None
        ]
        pair = (holes > 0) & (nb > 0)
        pairs.append((holes[pair], nb[pair]))
    ids = np.concatenate([i for i, _ in pairs])
    vals = np.concatenate([v for _, v in pairs])
    lo = np.full(n + 1, 1 << 30, np.int64)
    np.minimum.at(lo, ids, vals)
    count = np.bincount(ids, minlength=n + 1)
    close = vals - lo[ids] <= span_mm
    near = np.bincount(ids[close], minlength=n + 1)
    total = np.bincount(ids[close], weights=vals[close].astype(np.float64), minlength=n + 1)
    size = np.bincount(holes.ravel(), minlength=n + 1)
    filled = 0
    for i in range(1, n + 1):
        if count[i] == 0 or near[i] < surface_share * count[i]:
            continue
        z = total[i] / near[i]
        if size[i] * z * z > max_sum_z2:
            continue
        out[holes == i] = np.uint16(np.floor(z + 0.5))
        filled += 1
    return out, filled


def thin_edges_reference(depth, radius, jump_mm, min_farther):
    """`fattening.thin_edges` in whole-array numpy: for every offset within Chebyshev
    `radius`, the shifted frame (no depth off the image) offers its depth to the pixels it is
    farther than by more than `jump_mm`; a pixel with depth and at least `min_farther` offers
    takes the largest."""
    d = depth.astype(np.int64)
    h, w = d.shape
    padded = np.pad(d, radius)
    best = d.copy()
    offers = np.zeros(d.shape, np.int64)
    for dv in range(-radius, radius + 1):
        for du in range(-radius, radius + 1):
            nb = padded[radius + dv : radius + dv + h, radius + du : radius + du + w]
            offer = (d > 0) & (nb - d > jump_mm)
            offers += offer
            best = np.where(offer, np.maximum(best, nb), best)
    return np.where(offers >= min_farther, best, d).astype(np.uint16)


# --- the static cell's background gate (background.gate_background) ------------------------


def gate_background_reference(depth, values, background, tolerance, gate, apply=True):
    """`background.gate_background` in whole-array numpy: (the gate after it, pixels that
    match the background, pixels farther than it by more than the tolerance). A pixel is
    compared where the background is valid (tolerance >= 0) and the frame has depth and a
    model value; float32 differences, as the kernel takes them."""
    seen = (tolerance >= 0) & (depth > 0) & (values > 0)
    diff = depth.astype(np.float32) - background.astype(np.float32)
    match = seen & (np.abs(diff) <= tolerance)
    missing = seen & ~match & (diff > tolerance)
    out = gate | match if apply else gate.copy()
    return out, int(match.sum()), int(missing.sum())


# --- one surface, one thing (surfaces.vote_surfaces) ---------------------------------------


def vote_surfaces_reference(labels_in, depth, step_mm, voting, bin_mm):
    """`surfaces.vote_surfaces` in numpy and scipy: (labels after it, pixels relabelled,
    surfaces that changed). Voting pixels with depth are the graph's nodes; 4-neighbours
    are joined when their depths differ by at most the step table's entry at the nearer
    depth's bin (the last entry beyond it); each component takes its majority of the two
    voting classes, a tie leaving it as it is."""
    lab = labels_in.copy()
    h, w = lab.shape
    d = np.asarray(depth, np.float32)
    node = voting[lab] & (d > 0)
    idx = np.arange(h * w).reshape(h, w)
    a_all, b_all = [], []
    for da, db in (((slice(None), slice(1, None)), (slice(None), slice(None, -1))),
                   ((slice(1, None), slice(None)), (slice(None, -1), slice(None)))):  # fmt: skip
        near = np.minimum(d[da], d[db]).astype(np.int64) // bin_mm
        limit = step_mm[np.minimum(near, len(step_mm) - 1)]
        ok = node[da] & node[db] & (np.abs(d[da] - d[db]) <= limit)
        a_all.append(idx[da][ok])
        b_all.append(idx[db][ok])
    a, b = np.concatenate(a_all), np.concatenate(b_all)
    graph = sparse.coo_matrix((np.ones(len(a)), (a, b)), shape=(h * w, h * w))
    _, comp = sparse.csgraph.connected_components(graph, directed=False)
    first, second = np.flatnonzero(voting)
    changed, surfaces = 0, 0
    for c in np.unique(comp.reshape(h, w)[node]):
        members = node & (comp.reshape(h, w) == c)
        n1 = int((lab[members] == first).sum())
        n2 = int((lab[members] == second).sum())
        if n1 == n2:
            continue
        winner = first if n1 > n2 else second
        flip = members & (lab != winner)
        if flip.any():
            changed += int(flip.sum())
            surfaces += 1
            lab[flip] = winner
    return lab, changed, surfaces


# --- safety: separation ---------------------------------------------------------------------


def capsule_distances_reference(points, a, b, radius):
    """`separation.point_distances` in numpy: every point against every capsule at once;
    (n,) distance to the nearest capsule's surface (0 inside) and (n,) its index."""
    points = np.asarray(points, np.float64)[:, None, :]  # (n, 1, 3)
    axis = (b - a)[None]  # (1, m, 3)
    length2 = np.einsum("...i,...i->...", axis, axis)
    along = np.einsum("...i,...i->...", points - a[None], axis)
    t = np.clip(np.divide(along, length2, out=np.zeros_like(along), where=length2 > 0), 0, 1)
    closest = a[None] + t[..., None] * axis
    d = np.linalg.norm(points - closest, axis=-1) - radius[None]  # (n, m)
    index = np.argmin(d, axis=1)
    return np.maximum(d[np.arange(len(d)), index], 0.0), index


def label4_reference(mask):
    """`separation.label4` with scipy: 4-connected components numbered in raster order of
    their first pixel (ndimage's own order), -1 off the mask."""
    ids, count = ndimage.label(mask)
    return ids.astype(np.int32) - 1, int(count)


def grow_mask_reference(mask, ru, rv):
    """`robot._grow_kernel` in numpy: the mask shifted by every integer offset (du, dv)
    with (du / ru)^2 + (dv / rv)^2 <= 1, or-ed together."""
    h, w = mask.shape
    out = np.zeros_like(mask)
    padded = np.zeros((h + 2 * h, w + 2 * w), bool)
    padded[h : 2 * h, w : 2 * w] = mask
    for dv in range(-int(rv), int(rv) + 1):
        for du in range(-int(ru), int(ru) + 1):
            if (du / ru) ** 2 + (dv / rv) ** 2 <= 1 + 1e-12:
                out |= padded[h - dv : 2 * h - dv, w - du : 2 * w - du]
    return out


def _segment_closest_reference(points, a, b):
    """(n, m, 3) closest points of segments a..b (m, 3) to points (n, 3)."""
    axis = (b - a)[None]
    length2 = np.einsum("...i,...i->...", axis, axis)
    along = np.einsum("...i,...i->...", points[:, None] - a[None], axis)
    t = np.clip(np.divide(along, length2, out=np.zeros_like(along), where=length2 > 0), 0, 1)
    return a[None] + t[..., None] * axis


def triangle_distances_reference(points, triangles):
    """`surface.triangle_closest` in numpy: (n, m) distance of every point to every
    triangle, as the nearer of the point's projection on the face (when it falls inside)
    and the three edges."""
    points = np.asarray(points, np.float64)
    a, b, c = (np.asarray(triangles, np.float64)[:, k] for k in range(3))
    edges = [
        np.linalg.norm(points[:, None] - _segment_closest_reference(points, p, q), axis=-1)
        for p, q in ((a, b), (b, c), (c, a))
    ]
    best = np.minimum(np.minimum(edges[0], edges[1]), edges[2])
    normal = np.cross(b - a, c - a)
    area2 = np.linalg.norm(normal, axis=1)
    ok = area2 > 1e-12
    unit = np.divide(normal, area2[:, None], out=np.zeros_like(normal), where=ok[:, None])
    height = np.einsum("nmi,mi->nm", points[:, None] - a[None], unit)
    foot = points[:, None] - height[..., None] * unit[None]
    inside = np.ones(height.shape, bool)
    for p, q in ((a, b), (b, c), (c, a)):  # the foot is on the inner side of every edge
        side = np.einsum("nmi,mi->nm", np.cross(q - p, foot - p[None]), unit)
        inside &= side >= 0
    face = np.where(inside & ok[None], np.abs(height), np.inf)
    return np.minimum(best, face)


def primitive_distances_reference(points, kind, size, center, rot):
    """`surface.primitive_closest` in numpy: (n,) distance of every point to one primitive
    (0 inside), from the point's coordinates in the primitive's frame."""
    local = (np.asarray(points, np.float64) - center) @ rot  # rows: rot.T @ (p - c)
    if kind == BOX:
        return np.linalg.norm(np.maximum(np.abs(local) - size[:3], 0.0), axis=1)
    if kind == CYLINDER:
        radial = np.maximum(np.hypot(local[:, 0], local[:, 1]) - size[0], 0.0)
        axial = np.maximum(np.abs(local[:, 2]) - size[1], 0.0)
        return np.hypot(radial, axial)
    half = size[1] if kind == CAPSULE else 0.0
    along = local[:, 2] - np.clip(local[:, 2], -half, half)
    return np.maximum(np.sqrt(local[:, 0] ** 2 + local[:, 1] ** 2 + along**2) - size[0], 0.0)


def cell_channels_reference(labels, valid, heights_mm, depth, proba, cell, table, posterior_table):
    """`context_check_kernels.cell_channels`, one cell at a time with numpy."""
    hc, wc = labels.shape[0] // cell, labels.shape[1] // cell
    n_cols, n_post = table.shape[1], posterior_table.shape[1]
    classes = min(proba.shape[2], posterior_table.shape[0])
    chan = np.zeros((hc, wc, n_cols + 1 + n_post), np.float32)
    depth_sum = np.zeros((hc, wc))
    n_valid = np.zeros((hc, wc), np.int32)
    parts = np.zeros((hc, wc), np.int32)
    for i in range(hc):
        for j in range(wc):
            block = (slice(i * cell, (i + 1) * cell), slice(j * cell, (j + 1) * cell))
            lab, ok = labels[block].ravel(), valid[block].ravel()
            rows = table[lab].astype(np.float64)
            rows[~ok] = 0.0
            rows[~ok, n_cols - 1] = 1.0  # no depth or the floor gate: background
            chan[i, j, :n_cols] = rows.sum(0) / (cell * cell)
            n_valid[i, j] = ok.sum()
            parts[i, j] = (table[lab, 0] > 0).sum()
            depth_sum[i, j] = depth[block].ravel()[ok].astype(np.float64).sum()
            h = heights_mm[block].ravel()[ok].astype(np.float64)
            h = h[np.isfinite(h)]
            if h.size:
                chan[i, j, n_cols] = h.mean() / 1000.0
            p = proba[block].reshape(-1, proba.shape[2])[ok, :classes].astype(np.float64)
            if p.size:
                chan[i, j, n_cols + 1 :] = (p @ posterior_table[:classes]).mean(0)
    return chan, depth_sum, n_valid, parts


def cell_features_reference(
    chan, cells_per_cm, rows, cols, rings_cm, boxes_cm, sines, cosines, height
):
    """`context_check_kernels.cell_features`, every box summed directly over its cells;
    channel `height` is read relative to the cell's own."""
    hc, wc, nc = chan.shape

    def box_mean(r, c, k):
        r0, r1 = np.clip([r - k, r + k + 1], 0, hc)
        c0, c1 = np.clip([c - k, c + k + 1], 0, wc)
        area = max((r1 - r0) * (c1 - c0), 1)
        return chan[r0:r1, c0:c1].astype(np.float64).sum((0, 1)) / area

    out = []
    for r, c in zip(rows, cols, strict=True):
        s = cells_per_cm[r, c]
        row = [chan[r, c].astype(np.float64), box_mean(r, c, 1)]
        for ring, box in zip(rings_cm, boxes_cm, strict=True):
            k = int(np.floor(box * 0.5 * s + 0.5))
            boxes = []
            for sn, cs in zip(sines, cosines, strict=True):
                b = box_mean(r + int(np.floor(ring * s * sn + 0.5)),
                             c + int(np.floor(ring * s * cs + 0.5)), k)  # fmt: skip
                b[height] -= chan[r, c, height]
                boxes.append(b)
            boxes = np.array(boxes)
            row += [boxes.mean(0), boxes.max(0), boxes.min(0)]
        out.append(np.concatenate(row))
    return np.array(out, np.float32).reshape(len(rows), nc * (2 + 3 * len(rings_cm)))


def tree_ensemble_reference(x, feature, threshold, left, right, value, roots):
    """(n,) each row's sum over the trees, in tree order, of the leaf it reaches by walking
    the linked nodes (`TreeEnsemble`'s arrays): x[feature] <= threshold goes left, the rest
    (NaN too) right, feature -1 is a leaf."""
    out = np.zeros(len(x))
    for i, row in enumerate(np.asarray(x, np.float64)):
        total = 0.0
        for root in roots:
            node = root
            while feature[node] >= 0:
                node = left[node] if row[feature[node]] <= threshold[node] else right[node]
            total += value[node]
        out[i] = total
    return out


def fold_prior_reference(proba, valid, cell, groups, has_prior, class_group, alpha, eps):
    """`context_prior_kernels.fold_prior` by blocks: (posteriors after, argmax after); the
    posteriors of valid pixels in cells with a prior weighted by ((q_g + eps) / (m_g +
    eps)) ** alpha and normalised, m_g the cell's mean posterior mass in group g."""
    proba = proba.astype(np.float64)
    hc, wc = has_prior.shape
    n_groups = groups.shape[2]
    onehot = np.zeros((proba.shape[2], n_groups))
    onehot[np.arange(proba.shape[2]), class_group[: proba.shape[2]]] = 1.0
    for i in range(hc):
        for j in range(wc):
            block = np.s_[i * cell : (i + 1) * cell, j * cell : (j + 1) * cell]
            v = valid[block]
            if not has_prior[i, j] or not v.any():
                continue
            p = proba[block][v]
            mass = (p @ onehot).mean(axis=0)
            weight = ((groups[i, j] + eps) / (mass + eps)) ** alpha
            p = p * (onehot @ weight)
            total = p.sum(axis=1, keepdims=True)
            p = np.where(total > 0, p / np.where(total > 0, total, 1.0), p)
            sub = proba[block]
            sub[v] = p
            proba[block] = sub
    return proba.astype(np.float32), proba.argmax(axis=2)
