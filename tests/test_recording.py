"""MCAP recordings keep the exact wire bytes, appear atomically and survive being cut short."""

import os
import resource
import signal

import numpy as np
import pytest

from topseg.core.camera import KINECT_V1
from topseg.core.formats import recording, wire
from topseg.core.formats.recording import RecordingError, RecordingWriter


def wire_messages(rng, n=6):
    """n depth frames with ground truth, as a driver publishes them, plus one stats message."""
    out = []
    for i in range(n):
        depth = rng.integers(0, 4000, KINECT_V1.shape, dtype=np.uint16)
        truth = rng.integers(0, 11, KINECT_V1.shape, dtype=np.uint8)
        stamp = 1_700_000_000_000_000_000 + i * 33_000_000
        out.append(
            (wire.depth_key(), wire.encode_depth(wire.DepthFrame(depth, seq=i, stamp_ns=stamp)))
        )
        out.append((wire.truth_key(), wire.encode_labels(wire.LabelFrame(truth, i, stamp))))
    out.append(
        (wire.stats_key(), wire.encode_stats({"stamp_ns": 1, "timings_ms": {}, "counts": {}}))
    )
    return out


def test_round_trip_exact_bytes_one_channel_per_key(tmp_path):
    msgs = wire_messages(np.random.default_rng(0))
    path = tmp_path / "r.mcap"
    with RecordingWriter(path, metadata={"note": "test"}) as w:
        for i, (key, data) in enumerate(msgs):
            w.write(key, data, log_time_ns=1000 + i)
        assert not path.exists()  # only the temporary file exists while recording
    assert path.exists()
    assert [p.name for p in tmp_path.iterdir()] == ["r.mcap"]  # no temp file left behind

    info = recording.RecordingInfo()
    back = list(recording.read_messages(path, info=info))
    assert [(m.key, m.data) for m in back] == msgs
    assert [m.log_time_ns for m in back] == list(range(1000, 1000 + len(msgs)))
    assert info.counts == {wire.depth_key(): 6, wire.truth_key(): 6, wire.stats_key(): 1}
    assert not info.truncated
    assert info.metadata["topseg"]["note"] == "test"
    # per-channel sequence numbers
    assert [m.sequence for m in back if m.key == wire.truth_key()] == list(range(6))
    # the real mcap reader (summary, seeking) agrees on channels and encodings
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    topics = {c.topic: c.message_encoding for c in summary.channels.values()}
    assert topics == dict.fromkeys(info.counts, "msgpack")
    # key filter
    only = list(recording.read_messages(path, keys=[wire.truth_key()]))
    assert [m.data for m in only] == [d for k, d in msgs if k == wire.truth_key()]


def test_cut_short_file_reads_its_complete_prefix(tmp_path):
    msgs = wire_messages(np.random.default_rng(1), n=8)
    full = tmp_path / "full.mcap"
    with RecordingWriter(full, chunk_size=200_000) as w:
        for key, data in msgs:
            w.write(key, data)
    blob = full.read_bytes()
    seen = set()
    for cut in np.linspace(16, len(blob) - 1, 23).astype(int):
        part = tmp_path / "part.mcap"
        part.write_bytes(blob[:cut])
        info = recording.RecordingInfo()
        back = [(m.key, m.data) for m in recording.read_messages(part, info=info)]
        assert back == msgs[: len(back)]  # a prefix, byte for byte
        assert info.truncated
        seen.add(len(back))
    assert len(seen) > 3  # cuts at different places keep different amounts


def test_disk_full_keeps_what_was_written(tmp_path):
    """A real write failure: the file size limit makes write() fail with EFBIG."""
    msgs = wire_messages(np.random.default_rng(2), n=10)
    path = tmp_path / "full-disk.mcap"
    old_limit = resource.getrlimit(resource.RLIMIT_FSIZE)
    old_handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (3_000_000, old_limit[1]))
    written = 0
    try:
        w = RecordingWriter(path, chunk_size=400_000)
        with pytest.raises(RecordingError, match="kept"):
            for key, data in msgs:
                w.write(key, data)
                written += 1
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, old_limit)
        signal.signal(signal.SIGXFSZ, old_handler)
    assert 0 < written < len(msgs)
    assert path.exists() and not list(tmp_path.glob(".*partial"))
    info = recording.RecordingInfo()
    back = [(m.key, m.data) for m in recording.read_messages(path, info=info)]
    assert 0 < len(back) <= written
    assert back == msgs[: len(back)]
    assert info.truncated


def test_discard_and_bad_paths(tmp_path):
    w = RecordingWriter(tmp_path / "x.mcap")
    w.write("topseg/a/b/depth", b"123")
    w.discard()
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(RecordingError, match="does not exist"):
        RecordingWriter(tmp_path / "missing" / "x.mcap")
    with pytest.raises(RecordingError, match="directory"):
        RecordingWriter(tmp_path)
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(os.urandom(1000))
    with pytest.raises(RecordingError, match="not an MCAP"):
        list(recording.read_messages(junk))
    with pytest.raises(RecordingError, match="cannot read"):
        list(recording.read_messages(tmp_path / "nope.mcap"))
