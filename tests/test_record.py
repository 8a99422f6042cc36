"""`topseg record` as a real process: the MCAP it writes holds exactly the bytes published."""

import os
import resource
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import zenoh
from netutil import free_port

from topseg.core.camera import KINECT_V1
from topseg.core.formats import recording, wire
from topseg.services.zenoh_session import open_session

K = KINECT_V1.scaled_to(160, 120)


def start_recorder(port, out, *extra, preexec_fn=None):
    cmd = [sys.executable, "-m", "topseg.services.cli", "-v", "record", "--out", str(out)]
    cmd += ["--zenoh-port", str(port), *extra]
    return subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=preexec_fn
    )


class Publisher:
    """The test's own session, publishing wire messages under BLOCK (nothing lost)."""

    def __init__(self, port, cell):
        self.session = open_session(port=port)
        self.cell = cell
        self.pubs = {}

    def pub(self, key):
        if key not in self.pubs:
            self.pubs[key] = self.session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK
            )
        return self.pubs[key]

    def wait_matched(self, keys, timeout=20.0):
        deadline = time.monotonic() + timeout
        while not all(self.pub(k).matching_status.matching for k in keys):
            assert time.monotonic() < deadline, "the recorder never subscribed"
            time.sleep(0.02)

    def close(self):
        self.session.close()


@pytest.fixture
def publisher():
    made = []

    def make(port, cell):
        made.append(Publisher(port, cell))
        return made[-1]

    yield make
    for p in made:
        p.close()


def messages(cell, n=4, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        depth = rng.integers(0, 5000, K.shape, dtype=np.uint16)
        lab = rng.integers(0, 11, K.shape, dtype=np.uint8)
        out.append((wire.depth_key(cell), wire.encode_depth(wire.DepthFrame(depth, K, i, 10 + i))))
        out.append((wire.labels_key(cell), wire.encode_labels(wire.LabelFrame(lab, i, 10 + i))))
        out.append((wire.truth_key(cell), wire.encode_labels(wire.LabelFrame(lab, i, 10 + i))))
    return out


def test_records_exact_bytes_of_default_keys_and_stops_on_sigterm(tmp_path, publisher):
    port, cell = free_port(), "rec1"
    out = tmp_path / "session.mcap"
    proc = start_recorder(port, out)
    pub = publisher(port, cell)
    msgs = messages(cell)
    stats = (
        wire.stats_key(cell),
        wire.encode_stats({"stamp_ns": 1, "timings_ms": {}, "counts": {}}),
    )
    junk = (wire.depth_key(cell), b"\xc1 not msgpack")  # recorded as is: a recording keeps the wire
    try:
        pub.wait_matched([k for k, _ in msgs])
        for key, data in [*msgs, stats, junk]:
            pub.pub(key).put(data)
        time.sleep(0.5)
        assert not out.exists()  # still recording, under a temporary name
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    info = recording.RecordingInfo()
    back = [(m.key, m.data) for m in recording.read_messages(out, info=info)]
    # stats are not recorded by default; bytes and each key's order are kept (zenoh does
    # not order messages across keys)
    for key in {k for k, _ in msgs}:
        assert [d for k, d in back if k == key] == [d for k, d in [*msgs, junk] if k == key]
    assert len(back) == len(msgs) + 1
    assert not info.truncated
    assert sorted(info.counts) == sorted(
        {wire.depth_key(cell), wire.labels_key(cell), wire.truth_key(cell)}
    )
    assert not list(tmp_path.glob(".*partial"))


def test_count_and_chosen_keys(tmp_path, publisher):
    port, cell = free_port(), "rec2"
    out = tmp_path / "stats.mcap"
    key = wire.stats_key(cell)
    proc = start_recorder(port, out, "--keys", f"topseg/{cell}/*/stats", "--count", "3")
    pub = publisher(port, cell)
    sent = [
        wire.encode_stats({"stamp_ns": i, "timings_ms": {"crf": 1.5}, "counts": {}})
        for i in range(5)
    ]
    try:
        pub.wait_matched([key])
        for data in sent:
            pub.pub(key).put(data)
        rc = proc.wait(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert rc == 0, proc.stderr.read()
    assert [m.data for m in recording.read_messages(out)] == sent[:3]


def test_duration_ends_an_idle_recording(tmp_path):
    out = tmp_path / "idle.mcap"
    t0 = time.monotonic()
    proc = start_recorder(free_port(), out, "--duration", "0.5")
    rc = proc.wait(timeout=30)
    assert rc == 0, proc.stderr.read()
    assert time.monotonic() - t0 >= 0.5
    assert recording.inspect(out).counts == {}  # a valid, empty recording


def test_full_disk_stops_cleanly_and_keeps_what_was_written(tmp_path, publisher):
    def small_disk():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (2_500_000, resource.RLIM_INFINITY))

    port, cell = free_port(), "rec3"
    out = tmp_path / "full.mcap"
    proc = start_recorder(port, out, preexec_fn=small_disk)
    pub = publisher(port, cell)
    rng = np.random.default_rng(5)
    key = wire.depth_key(cell)
    sent = []
    try:
        pub.wait_matched([key])
        for i in range(12):  # 12 incompressible 600 KB frames: far past the 2.5 MB limit
            depth = rng.integers(0, 65536, KINECT_V1.shape, dtype=np.uint16)
            sent.append(wire.encode_depth(wire.DepthFrame(depth, KINECT_V1, i, i)))
            pub.pub(key).put(sent[-1])
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 2, err
    assert "topseg record: error:" in err and "stays readable" in err and "Traceback" not in err
    info = recording.RecordingInfo()
    back = [m.data for m in recording.read_messages(out, info=info)]
    assert 0 < len(back) < len(sent)
    assert back == sent[: len(back)]
    assert info.truncated


def test_bad_arguments(tmp_path):
    proc = start_recorder(free_port(), tmp_path / "no" / "dir" / "x.mcap")
    assert proc.wait(timeout=30) == 2
    assert "does not exist" in proc.stderr.read()
    proc = start_recorder(free_port(), tmp_path / "x.mcap", "--keys", "topseg//depth")
    assert proc.wait(timeout=30) == 2
    assert "key expression" in proc.stderr.read()
    assert not os.path.exists(tmp_path / "x.mcap")
