"""Malformed input: the wire decoder under fuzzing (one error type, bounded memory), a real
worker fed a stream of damaged messages over Zenoh, `topseg segment` on damaged PNGs, and
damaged recordings through segment and replay. (test_wire.py fuzzes field values and
truncation; this adds flipped bytes, lying container headers and memory bounds.)"""

import struct
import subprocess
import sys
import tracemalloc
import zlib
from pathlib import Path

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from netutil import Services, Tap, free_port, wait_for
from PIL import Image

from topseg.core import forest
from topseg.core.camera import KINECT_V1, PAPER_MOUNT, TopViewMount
from topseg.core.formats import recording, wire
from topseg.core.formats.wire import WireError
from topseg.core.synth.procedural import procedural_frame
from topseg.drivers import SourceError, SourceOptions, open_source

ROOT = Path(__file__).resolve().parent.parent
MODEL = ROOT / "models" / "default.npz"
K = KINECT_V1.scaled_to(160, 120)
FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def good_depth(seq=0, rng=None, k=K):
    depth, _ = procedural_frame(
        rng or np.random.default_rng(seq), TopViewMount(k, PAPER_MOUNT.height_mm)
    )
    return wire.encode_depth(wire.DepthFrame(depth, k, seq, 1000 + seq, "cam0"))


GOOD = good_depth()
FULL = good_depth(k=KINECT_V1)
#: a version-2 message with a (tilted) mount: the mount map is damaged like any other field
MOUNTED = wire.encode_depth(
    wire.DepthFrame(
        wire.decode_depth(GOOD).depth, K, 1, 1001, "cam0", TopViewMount(K, 3150.0, 3.5, -2.0)
    )
)


def decode_bounded(decode, data: bytes):
    """Decode under tracemalloc: only WireError, and never much more memory than the input."""
    tracemalloc.start()
    try:
        decode(data)
    except WireError:
        pass
    finally:
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    assert peak < 3 * len(data) + (1 << 20), f"{peak} bytes for a {len(data)}-byte message"


@given(st.data())
@FUZZ
def test_flipped_bytes_of_valid_messages(data):
    msg = bytearray(data.draw(st.sampled_from([GOOD, FULL, MOUNTED])))
    for _ in range(data.draw(st.integers(1, 8))):
        # most damage lands in the fields: the first 200 bytes hold those before the data, the
        # last 250 those after it (the intrinsics and the mount)
        i = data.draw(
            st.integers(0, 199)
            | st.integers(len(msg) - 250, len(msg) - 1)
            | st.integers(0, len(msg) - 1)
        )
        msg[i] = data.draw(st.integers(0, 255))
    decode_bounded(wire.decode_depth, bytes(msg))
    decode_bounded(wire.decode_labels, bytes(msg))


LENGTH_HEADERS = [b"\xc6", b"\xdb", b"\xdd", b"\xdf", b"\xc9\x05"]  # bin32 str32 arr32 map32 ext32


@given(st.sampled_from(LENGTH_HEADERS), st.integers(0, 2**32 - 1), st.binary(max_size=64))
@FUZZ
def test_container_headers_that_claim_gigabytes(head, claimed, tail):
    body = head[:1] + struct.pack(">I", claimed) + head[1:] + tail
    decode_bounded(wire.decode_depth, body)
    # the same lie as the value of `data` inside an otherwise good map
    good = msgpack.packb({**msgpack.unpackb(GOOD), "data": b""})
    cut = good.rindex(b"\xc4\x00")  # the empty bin of `data`
    decode_bounded(wire.decode_depth, good[:cut] + b"\xc6" + struct.pack(">I", claimed) + tail)


@given(st.integers(-(2**63), 2**64 - 1), st.integers(-(2**63), 2**64 - 1), st.binary(max_size=99))
@FUZZ
def test_huge_dimensions(width, height, data):
    msg = {**msgpack.unpackb(GOOD), "width": width, "height": height, "data": data}
    decode_bounded(wire.decode_depth, msgpack.packb(msg))


# ---------------------------------------------------------------------------- a real worker


def bad_messages(n: int, seed: int) -> list[bytes]:
    """n payloads that do not decode: random bytes, cuts, flips, wrong types, lying sizes."""
    rng = np.random.default_rng(seed)
    base = msgpack.unpackb(GOOD)
    values = [None, True, -1, 2**64 - 1, 1e300, float("nan"), "x" * 300, b"\0" * 7, [1], {"a": 1}]
    out = []
    while len(out) < n:
        kind = len(out) % 5
        if kind == 0:
            p = rng.bytes(int(rng.integers(0, 3000)))
        elif kind == 1:
            p = GOOD[: int(rng.integers(0, len(GOOD)))]
        elif kind == 2:
            b = bytearray(GOOD)
            for i in rng.integers(0, 150, 4):
                b[i] = int(rng.integers(0, 256))
            p = bytes(b)
        elif kind == 3:
            field = sorted(base)[int(rng.integers(0, len(base)))]
            p = msgpack.packb({**base, field: values[int(rng.integers(0, len(values)))]})
        else:
            side = int(rng.integers(0, 2**31))
            p = msgpack.packb({**base, "width": side, "height": side})
        try:
            wire.decode_depth(p)
        except WireError:
            out.append(p)
    return out


def test_worker_drops_and_counts_a_stream_of_damaged_messages_and_labels_the_good_ones(tmp_path):
    services, port, cell = Services(), free_port(), "rin1"
    tap = Tap(port, cell)
    try:
        wk = services("worker", "--model", MODEL, "--lossless", "--crf", "none", "--cameras",
                      f"{cell}/cam0", "--zenoh-port", port)  # fmt: skip
        tap.publish(GOOD)  # declares the publisher; the worker may not be there yet
        wk.wait_line("worker ready", 120)
        wait_for(lambda: tap.matched, 30, "the worker's subscriber")
        bad = bad_messages(300, 1)
        goods = [good_depth(seq) for seq in range(1, 7)]
        t0 = tap.labels[-1][0] if tap.labels else 0.0
        for i, payload in enumerate(bad):
            tap.publish(payload)
            if i % 50 == 49:
                tap.publish(goods[i // 50])
        wait_for(lambda: len(tap.labels_after(t0)) >= len(goods), 60, "labels of the good frames")
        wait_for(
            lambda: tap.stats and tap.stats[-1]["counts"]["rejected"] == len(bad), 20, "the count"
        )
        assert [x[1] for x in tap.labels_after(t0)][-len(goods) :] == list(range(1, 7))
        assert wk.alive()
        assert wk.stop() == 0, wk.err
    finally:
        services.close()
        tap.close()
    warnings = [line for line in wk.err.splitlines() if "rejected)" in line]
    assert 10 <= len(warnings) <= 13  # the first ten, then one per hundred: the log is not flooded
    assert "Traceback" not in wk.err


# ---------------------------------------------------------------------------- segment


@pytest.fixture(scope="module")
def small_model(tmp_path_factory):
    rng = np.random.default_rng(2)
    frames = [procedural_frame(rng) for _ in range(3)]
    cfg = forest.TrainConfig(n_trees=1, max_depth=5, frames_per_tree=3, pixels_per_frame=200,
                             n_candidates=8, n_thresholds=8)  # fmt: skip
    trained = forest.train_forest(
        np.stack([d for d, _ in frames]), np.stack([t for _, t in frames]), cfg, seed=0
    )
    path = tmp_path_factory.mktemp("model") / "m.npz"
    forest.save_model(path, trained)
    return path, trained


def segment(*args):
    cmd = [sys.executable, "-m", "topseg.services.cli", "segment", "--crf", "none", *map(str, args)]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300)


def png_chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def huge_png(width: int, height: int) -> bytes:
    """A 16-bit grey PNG header claiming width x height, with a few bytes of pixels."""
    ihdr = struct.pack(">IIBBBBB", width, height, 16, 0, 0, 0, 0)
    idat = zlib.compress(b"\0" * 1000)
    return b"\x89PNG\r\n\x1a\n" + png_chunk(b"IHDR", ihdr) + png_chunk(b"IDAT", idat)


def test_segment_skips_damaged_pngs_with_one_line_each_and_does_the_rest(small_model, tmp_path):
    path, trained = small_model
    depth, _ = procedural_frame(np.random.default_rng(4))
    src = tmp_path / "in"
    src.mkdir()
    Image.fromarray(depth).save(src / "a_good.png")
    Image.fromarray(depth).save(src / "z_good.png")
    whole = (src / "a_good.png").read_bytes()
    (src / "b_truncated.png").write_bytes(whole[: len(whole) // 2])
    Image.fromarray((depth // 256).astype(np.uint8)).save(src / "c_8bit.png")
    (src / "d_text.png").write_text("this is not a PNG\n")
    (src / "e_huge.png").write_bytes(huge_png(60000, 60000))
    (src / "f_big.png").write_bytes(huge_png(8000, 8000))  # under PIL's bomb limit: 128 MB
    Image.fromarray(np.zeros((48, 64), np.uint16)).save(src / "g_other_camera.png")
    r = segment(src, "--model", path, "--out", tmp_path / "out")
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    for name in ("b_truncated", "c_8bit", "d_text", "e_huge", "f_big", "g_other_camera"):
        assert sum(name in line for line in lines) == 1, (name, r.stderr)
    assert "6 of 8 inputs" in lines[-1]
    assert "segmented 2 frames" in r.stdout
    expected = forest.predict_labels(trained, depth)
    for name in ("a_good", "z_good"):
        got = np.asarray(Image.open(tmp_path / "out" / f"{name}_labels.png"))
        np.testing.assert_array_equal(got, expected)


# ---------------------------------------------------------------------------- recordings


@pytest.fixture(scope="module")
def rec(tmp_path_factory):
    """A finished recording of 6 full-size frames (small chunks: a cut loses little)."""
    path = tmp_path_factory.mktemp("rec") / "whole.mcap"
    with recording.RecordingWriter(path, chunk_size=100_000) as w:
        for i in range(6):
            depth, _ = procedural_frame(np.random.default_rng(10 + i))
            t = 10**9 + i * 33_000_000
            w.write(wire.depth_key(), wire.encode_depth(wire.DepthFrame(depth, KINECT_V1, i, t)), t)
    return path


def damaged(rec: Path, tmp: Path) -> dict[str, Path]:
    from mcap.writer import Writer

    blob = rec.read_bytes()
    made = {}
    for name, data in {
        "truncated": blob[: len(blob) * 2 // 3],
        "garbage_appended": blob + np.random.default_rng(0).bytes(5000),
        "garbage_inside": blob[: len(blob) // 2] + bytes(4000) + blob[len(blob) // 2 + 4000 :],
        "not_mcap": b"\x89MCAP0\r\n" + bytes(100),
    }.items():
        made[name] = tmp / f"{name}.mcap"
        made[name].write_bytes(data)
    made["wrong_schema"] = tmp / "wrong_schema.mcap"
    with open(made["wrong_schema"], "wb") as f:  # a JSON channel on the depth key: not ours
        w = Writer(f)
        w.start()
        schema = w.register_schema("Depth", "jsonschema", b"{}")
        ch = w.register_channel(wire.depth_key(), "json", schema)
        for i in range(3):
            w.add_message(ch, log_time=i, publish_time=i, data=b'{"seq": %d}' % i)
        w.finish()
    return made


def replay_seqs(path: Path) -> list[int]:
    with open_source(f"replay:{path}", SourceOptions(realtime=False)) as src:
        return [f.depth.seq for f in src.frames()]


@pytest.mark.slow
def test_damaged_recordings_are_read_up_to_the_damage_or_refused_in_one_line(
    small_model, rec, tmp_path
):
    files = damaged(rec, tmp_path)
    assert replay_seqs(rec) == list(range(6))
    assert 0 < len(replay_seqs(files["truncated"])) < 6
    assert replay_seqs(files["garbage_appended"]) == list(range(6))
    assert len(replay_seqs(files["garbage_inside"])) < 6
    for name in ("not_mcap", "wrong_schema"):
        with pytest.raises(SourceError):
            replay_seqs(files[name])

    r = segment(*files.values(), "--model", small_model[0], "--out", tmp_path / "out")
    assert "Traceback" not in r.stderr, r.stderr
    got = sorted(p.name for p in (tmp_path / "out").glob("*_labels.png"))
    assert [g for g in got if g.startswith("garbage_appended")] == [
        f"garbage_appended_{i:06d}_labels.png" for i in range(6)
    ]
    assert 0 < len([g for g in got if g.startswith("truncated")]) < 6
    for name in ("not_mcap", "wrong_schema"):  # nothing readable: one line each, exit 2
        assert f"skipped {files[name]} holds no depth channel" in r.stderr
    assert r.returncode == 2 and "2 of 5 inputs" in r.stderr.splitlines()[-1]
