"""Model file: exact round trip; truncated, damaged, foreign and wrong-version files refused."""

import dataclasses
import json
import struct
import zipfile

import numpy as np
import pytest

from topseg.core import labels
from topseg.core.forest import (
    FORMAT_VERSION,
    Forest,
    ModelFileError,
    load_model,
    predict_proba,
    random_tree,
    save_model,
)
from topseg.core.forest.model_file import MAGIC


@pytest.fixture(scope="module")
def forest():
    rng = np.random.default_rng(0)
    return Forest.from_trees([random_tree(rng, d, 2, 80000.0) for d in (5, 6, 4)])


def rewrite(src, dst, change):
    """Copy the zip at `src` to `dst`, passing each member's bytes through change(name, data)."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for info in zin.infolist():
            data = change(info.filename, zin.read(info.filename))
            if data is not None:
                zout.writestr(info.filename, data)


def header_npy(header: dict) -> bytes:
    import io

    buf = io.BytesIO()
    np.save(buf, np.frombuffer(json.dumps(header).encode(), np.uint8))
    return buf.getvalue()


def test_round_trip_is_exact(tmp_path, forest):
    path = tmp_path / "m.npz"
    save_model(path, forest, {"camera": {"fx": 570.3}, "note": "test"})
    loaded, header = load_model(path)
    for name, arr in forest.arrays().items():
        got = loaded.arrays()[name]
        assert got.dtype == arr.dtype
        np.testing.assert_array_equal(got, arr)
    assert loaded.background_mm == forest.background_mm
    assert header["magic"] == MAGIC and header["format_version"] == FORMAT_VERSION
    assert header["labels"] == labels.as_json(labels.PAPER_NUM_CLASSES)
    assert loaded.n_classes == labels.PAPER_NUM_CLASSES
    assert header["camera"] == {"fx": 570.3} and header["note"] == "test"
    assert header["forest"]["n_trees"] == 3 and header["forest"]["max_depth"] == 6
    depth = np.random.default_rng(1).integers(500, 4000, (12, 16)).astype(np.uint16)
    np.testing.assert_array_equal(predict_proba(loaded, depth), predict_proba(forest, depth))
    assert [p.name for p in tmp_path.iterdir()] == ["m.npz"]  # no temp file left


def test_no_pickle_inside(tmp_path, forest):
    path = tmp_path / "m.npz"
    save_model(path, forest)
    with zipfile.ZipFile(path) as z:
        for name in z.namelist():
            assert np.load(z.open(name), allow_pickle=False).dtype != object


def test_missing_file_and_foreign_files(tmp_path):
    with pytest.raises(ModelFileError, match="no model file"):
        load_model(tmp_path / "absent.npz")
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a model at all")
    with pytest.raises(ModelFileError, match="not a zip"):
        load_model(junk)
    other = tmp_path / "other.npz"
    np.savez(other, a=np.arange(3))
    with pytest.raises(ModelFileError, match="no header"):
        load_model(other)


@pytest.mark.parametrize("keep", [0.1, 0.5, 0.9, 0.999])
def test_truncated_file_is_refused(tmp_path, forest, keep):
    path = tmp_path / "m.npz"
    save_model(path, forest)
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(ModelFileError, match="damaged or truncated"):
        load_model(path)


def test_flipped_bytes_are_refused(tmp_path, forest):
    path = tmp_path / "m.npz"
    save_model(path, forest)
    clean = path.read_bytes()
    rng = np.random.default_rng(0)
    spans = []
    with zipfile.ZipFile(path) as z:
        for info in z.infolist():  # local header: 30 bytes, then the name and an extra field
            name_len, extra_len = struct.unpack(
                "<HH", clean[info.header_offset + 26 : info.header_offset + 30]
            )
            spans.append((info.header_offset + 30 + name_len + extra_len, info.compress_size))
    for start, size in spans:  # one flip inside each member's data
        pos = start + int(rng.integers(size))
        bad = bytearray(clean)
        bad[pos] ^= 0x5A
        path.write_bytes(bytes(bad))
        with pytest.raises(ModelFileError):
            load_model(path)


def test_wrong_version_and_magic_are_refused(tmp_path, forest):
    src = tmp_path / "m.npz"
    save_model(src, forest)
    with zipfile.ZipFile(src) as z:
        header = json.loads(np.load(z.open("header.npy")).tobytes())
    for change, message in (
        ({"format_version": FORMAT_VERSION + 1}, "format version"),
        ({"magic": "something-else"}, "wrong magic"),
        ({"labels": labels.as_json()[:-1]}, "label table"),
    ):
        dst = tmp_path / "bad.npz"
        patched = header_npy({**header, **change})
        rewrite(src, dst, lambda name, data, p=patched: p if name == "header.npy" else data)
        with pytest.raises(ModelFileError, match=message):
            load_model(dst)


def test_a_model_of_every_class_round_trips_with_the_whole_table(tmp_path):
    rng = np.random.default_rng(3)
    trees = [random_tree(rng, 4, 2, 80000.0, n_classes=labels.NUM_CLASSES) for _ in range(2)]
    forest = Forest.from_trees(trees)
    save_model(tmp_path / "m.npz", forest)
    loaded, header = load_model(tmp_path / "m.npz")
    assert loaded.n_classes == labels.NUM_CLASSES
    assert [row["name"] for row in header["labels"]][-3:] == ["robot", "object", "no-depth"]
    depth = rng.integers(500, 4000, (12, 16)).astype(np.uint16)
    assert predict_proba(loaded, depth).shape == (12, 16, labels.NUM_CLASSES)


def test_a_header_table_that_is_not_a_prefix_of_todays_is_refused(tmp_path, forest):
    src = tmp_path / "m.npz"
    save_model(src, forest)
    with zipfile.ZipFile(src) as z:
        header = json.loads(np.load(z.open("header.npy")).tobytes())
    table = header["labels"]
    renamed = [*table[:-2], {**table[-2], "name": "desk"}, table[-1]]
    recoloured = [*table[:-2], {**table[-2], "color": [1, 2, 3]}, table[-1]]
    gap = [*table[:-2], table[-1]]  # 10 classes: the posteriors hold 11
    longer = labels.as_json()  # 13 classes: the posteriors hold 11
    for change, message in (
        (renamed, "label table"),
        (recoloured, "label table"),
        ([table[-1]], "label table"),
        ("labels", "label table"),
        (gap, "names 10 classes but the posteriors hold 11"),
        (longer, "names 13 classes but the posteriors hold 11"),
    ):
        dst = tmp_path / "bad.npz"
        patched = header_npy({**header, "labels": change})
        rewrite(src, dst, lambda name, data, p=patched: p if name == "header.npy" else data)
        with pytest.raises(ModelFileError, match=message):
            load_model(dst)


@pytest.mark.parametrize("member", ["left.npy", "posteriors.npy", "roots.npy"])
def test_missing_array_is_refused(tmp_path, forest, member):
    src, dst = tmp_path / "m.npz", tmp_path / "bad.npz"
    save_model(src, forest)
    rewrite(src, dst, lambda name, data: None if name == member else data)
    with pytest.raises(ModelFileError, match="lacks the arrays"):
        load_model(dst)


def _replace_array(src, dst, member, arr):
    import io

    buf = io.BytesIO()
    np.save(buf, arr)
    rewrite(src, dst, lambda name, data: buf.getvalue() if name == member else data)


def test_bad_indices_shapes_and_dtypes_are_refused(tmp_path, forest):
    src, dst = tmp_path / "m.npz", tmp_path / "bad.npz"
    save_model(src, forest)
    cases = []
    left = forest.left.copy()
    left[np.flatnonzero(left >= 0)[3]] = forest.n_nodes + 5  # child outside the array
    cases.append(("left.npy", left, "child index"))
    left = forest.left.copy()
    left[np.flatnonzero(left >= 0)[3]] = 0  # a cycle back to the root
    cases.append(("left.npy", left, "child index"))
    leaf = forest.leaf.copy()
    leaf[np.flatnonzero(leaf >= 0)[0]] = forest.posteriors.shape[0]
    cases.append(("leaf.npy", leaf, "leaf index"))
    cases.append(("roots.npy", np.array([0, forest.n_nodes], np.int32), "root index"))
    cases.append(("threshold.npy", forest.threshold.astype(np.float64), "dtype"))
    cases.append(("weights.npy", forest.weights[:, :1].copy(), "shape"))
    thr = forest.threshold.copy()
    thr[0] = np.nan
    cases.append(("threshold.npy", thr, "non-finite"))
    for member, arr, message in cases:
        _replace_array(src, dst, member, arr)
        with pytest.raises(ModelFileError, match=message):
            load_model(dst)


def test_save_is_atomic_and_header_is_checked(tmp_path, forest):
    path = tmp_path / "m.npz"
    save_model(path, forest, {"run": 1})
    with pytest.raises(ModelFileError, match="reserved"):
        save_model(path, forest, {"magic": "x"})
    with pytest.raises(ModelFileError, match="plain JSON"):
        save_model(path, forest, {"bad": object()})
    _, header = load_model(path)
    assert header["run"] == 1  # the failed saves left the old file intact
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.npz"]


def test_a_height_models_header_round_trips(tmp_path):
    from topseg.core.camera import KINECT_V1, TopViewMount
    from topseg.core.forest import FeatureConfig
    from topseg.core.forest.inputs import header_fields, trained_for
    from topseg.core.segmenter import Segmenter

    forest = Forest.from_trees([random_tree(np.random.default_rng(0), 3, 2, 1e5)])
    forest = dataclasses.replace(forest, nearest_off_image=True)  # as the features say
    features = FeatureConfig(n_features=50, canonical_height_mm=4500.0, reference_focal_px=500.0)
    tf = trained_for([TopViewMount(KINECT_V1, 2400.0), TopViewMount(KINECT_V1, 4500.0, 9.0)])
    save_model(tmp_path / "h.npz", forest, header_fields(features, tf))
    _, header = load_model(tmp_path / "h.npz")
    assert header["input"] == "height" and header["trained_for"] == tf
    seg = Segmenter.from_file(tmp_path / "h.npz")
    assert seg.reads_height and seg.features == features and seg.trained_for == tf


def test_what_probes_off_the_image_read_round_trips_and_old_files_read_background(tmp_path, forest):
    """`off_image` in the forest's header: "nearest" and "background" round-trip; a file
    without the key reads background, as its forest was trained (and so do the edge's gaps
    of a file without `edge_gaps`); another
    value, or a header whose features say otherwise than its forest, is refused."""
    from topseg.core.forest import FeatureConfig
    from topseg.core.forest.inputs import header_fields
    from topseg.core.segmenter import Segmenter

    src = tmp_path / "m.npz"
    for nearest in (True, False):
        save_model(src, dataclasses.replace(forest, nearest_off_image=nearest))
        loaded, header = load_model(src)
        assert loaded.nearest_off_image is nearest
        assert header["forest"]["off_image"] == ("nearest" if nearest else "background")
    with zipfile.ZipFile(src) as z:
        header = json.loads(np.load(z.open("header.npy")).tobytes())
    old = {**header, "forest": {k: v for k, v in header["forest"].items() if k != "off_image"}}
    dst = tmp_path / "old.npz"
    rewrite(src, dst, lambda name, data: header_npy(old) if name == "header.npy" else data)
    assert load_model(dst)[0].nearest_off_image is False
    bad = {**header, "forest": {**header["forest"], "off_image": "mirror"}}
    rewrite(src, dst, lambda name, data: header_npy(bad) if name == "header.npy" else data)
    with pytest.raises(ModelFileError, match="off_image 'mirror'"):
        load_model(dst)
    # a height model whose header lacks the key: neither its features nor its forest say it
    features = header_fields(FeatureConfig(off_image="background"))
    del features["features"]["off_image"], features["features"]["edge_gaps"]
    save_model(src, forest, features)
    with zipfile.ZipFile(src) as z:
        header = json.loads(np.load(z.open("header.npy")).tobytes())
    del header["forest"]["off_image"]
    rewrite(src, dst, lambda name, data: header_npy(header) if name == "header.npy" else data)
    seg = Segmenter.from_file(dst)
    assert seg.features.off_image == "background" and not seg.forest.nearest_off_image
    assert seg.features.edge_gaps == "background"  # nor the edge's gaps
    save_model(src, forest, header_fields(FeatureConfig()))  # features say nearest, forest not
    with pytest.raises(ModelFileError, match="what probes off the image read"):
        load_model(src)
