"""The static cell's background as an operator meets it: `topseg calibrate --background` from a
recording, `topseg segment --background`, the worker reporting a background that no longer
matches (and `topseg status` showing it), and the background's id on the wire and in both
forms of recording."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time

import msgpack
import numpy as np
import pytest
import zenoh
from netutil import free_port, wait_for
from PIL import Image
from test_background import CABINET, MOUNT, K, cell_depth, noisy

from topseg.core import labels as L
from topseg.core.background import fit_background, load_background, save_background
from topseg.core.formats import recording, wire
from topseg.core.formats.mount_file import read_mount_file
from topseg.core.formats.ros2_recording_writer import Ros2RecordingWriter
from topseg.services.live import status
from topseg.services.live.worker_background import MATCH_FRAMES, MISMATCH_FRAMES
from topseg.services.runtime.zenoh_session import open_session

BG_ID = "ab" * 32


def topseg(*args, timeout=300):
    return subprocess.run(
        [sys.executable, "-m", "topseg.services.cli", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def write_recording(path, frames, mount=MOUNT):
    with recording.RecordingWriter(path) as w:
        for i, depth in enumerate(frames):
            frame = wire.DepthFrame(depth, K, seq=i, stamp_ns=10**18 + i, mount=mount)
            w.write(wire.depth_key("c1", "cam0"), wire.encode_depth(frame))


def test_calibrate_records_the_background_that_segment_then_gates(tmp_path):
    rng = np.random.default_rng(20)
    empty = tmp_path / "empty.mcap"
    write_recording(empty, [noisy(cell_depth(), rng) for _ in range(25)])
    bg_file, mount_file = tmp_path / "etc" / "cell1-background.npz", tmp_path / "m.json"
    r = topseg(
        "calibrate", "--source", f"replay:{empty}", "--frames", 20,
        "--background", bg_file, "--out", mount_file,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert "background of replay:" in r.stdout and "from 20 frames" in r.stdout
    assert "background  100.0 %" in r.stdout and "unstable      0.0 %" in r.stdout
    bg = load_background(bg_file, K)
    assert f"id         {bg.id}" in r.stdout and f"background file {bg_file}" in r.stdout
    assert bg.frames == 20 and bg.sensor == "kinect_v1"
    mount = read_mount_file(mount_file)  # both from one run: the background keeps the mount
    assert abs(mount.height_mm - 3000.0) < 15 and bg.mount == mount
    assert np.abs(bg.depth_mm[CABINET] - 1200.0).max() < 10

    # later: the cabinet is gone in two frames, a person stands by the table in one
    later = tmp_path / "later.mcap"
    frames = [noisy(cell_depth(), rng) for _ in range(3)]
    person = cell_depth()
    person[30:50, 60:90] = 1400.0
    moved = cell_depth()
    moved[CABINET] = 3000.0
    frames += [noisy(person, rng), noisy(moved, rng), noisy(moved, rng)]
    write_recording(later, frames)
    out = tmp_path / "labels"
    r = topseg("segment", later, "--background", bg_file, "--out", out)
    assert r.returncode == 0, r.stderr
    assert f"background {bg_file} ({bg.id[:12]}): " in r.stdout
    assert "2 frames read over 2 % of it farther than recorded" in r.stdout
    pngs = sorted(out.glob("*_labels.png"))
    assert len(pngs) == 6
    first, with_person = (np.asarray(Image.open(p)) for p in pngs[:1] + pngs[3:4])
    assert (first == L.BACKGROUND).mean() > 0.99  # the static cell, cabinet and all
    # the person is not gated: labelled by the forest (but a corner of the box it is)
    assert (with_person[30:50, 60:90] != L.BACKGROUND).mean() > 0.97

    # another camera's background: its frames are skipped with one line naming the file
    other = tmp_path / "other.mcap"
    k = K.scaled_to(80, 60)
    with recording.RecordingWriter(other) as w:
        w.write(wire.depth_key(), wire.encode_depth(wire.DepthFrame(np.full((60, 80), 3000, np.uint16), k)))  # fmt: skip
    r = topseg("segment", other, "--background", bg_file, "--out", tmp_path / "o", "--mount", mount_file)  # fmt: skip
    assert r.returncode == 2
    assert f"background file {bg_file} was recorded with another camera" in r.stderr


def test_calibrate_needs_a_file_to_write(tmp_path):
    r = topseg("calibrate", "--source", "synthetic")
    assert r.returncode == 2 and "give --out FILE" in r.stderr and "--background FILE" in r.stderr
    r = topseg("calibrate", "--source", "synthetic", "--background", tmp_path / "b.npz",
               "--picture", tmp_path / "p.png")  # fmt: skip
    assert r.returncode == 2 and "--picture shows the mount: it goes with --out" in r.stderr


# ---------------------------------------------------------------------------- the worker


class Peer:
    """The test's session: publishes depth (BLOCK) and keeps labels and stats."""

    def __init__(self, port, cell):
        self.session = open_session(port=port)
        self.labels, self.stats = [], []
        self.pub = self.session.declare_publisher(
            wire.depth_key(cell, "cam0"), congestion_control=zenoh.CongestionControl.BLOCK
        )
        self.session.declare_subscriber(
            wire.labels_key(cell, "cam0"),
            lambda s: self.labels.append(wire.decode_labels(s.payload.to_bytes())),
        )
        self.session.declare_subscriber(
            wire.stats_key(cell, "cam0"),
            lambda s: self.stats.append(wire.decode_stats(s.payload.to_bytes())),
        )
        self.seq = 0

    def send(self, depth):
        self.pub.put(wire.encode_depth(wire.DepthFrame(depth, K, self.seq, time.time_ns(), "cam0", MOUNT)))  # fmt: skip
        self.seq += 1


def test_the_worker_reports_a_background_that_no_longer_matches(tmp_path):
    rng = np.random.default_rng(21)
    bg = fit_background([noisy(cell_depth(), rng) for _ in range(20)], K, "kinect_v1", MOUNT)
    path = tmp_path / "bg.npz"
    save_background(path, bg)
    port, cell = free_port(), "bgw"
    r = topseg("worker", "--background", path, "--zenoh-port", port, timeout=60)
    assert r.returncode == 2 and "exactly one --cameras" in r.stderr  # one camera's background
    bad = tmp_path / "bad.npz"
    bad.write_bytes(path.read_bytes()[:1000])
    r = topseg("worker", "--background", bad, "--cameras", f"{cell}/cam0", "--zenoh-port", port, timeout=60)  # fmt: skip
    last = r.stderr.strip().splitlines()[-1]
    assert r.returncode == 2 and last.startswith(
        f"topseg worker: error: background file {bad}: damaged or truncated"
    ), r.stderr

    peer = Peer(port, cell)
    cmd = [sys.executable, "-m", "topseg.services.cli", "-v", "worker", "--lossless",
           "--cameras", f"{cell}/cam0", "--background", str(path), "--zenoh-port", str(port)]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    moved = cell_depth()
    moved[CABINET] = 3000.0  # the cabinet went

    def phase(truth, n):
        for _ in range(n):
            peer.send(noisy(truth, rng))
        wait_for(lambda: len(peer.stats) >= peer.seq, 60, f"stats for {peer.seq} frames")

    try:
        wait_for(lambda: peer.pub.matching_status.matching, 120, "the worker's subscriber")
        phase(cell_depth(), 3)
        assert peer.stats[-1]["background"] == {
            "id": bg.id, "state": "match", "missing_share": pytest.approx(0, abs=0.002),
            "mismatch_share": 0.02, "sigmas": 3.0, "margin_mm": 5.0, "mismatches": 0,
        }  # fmt: skip
        phase(moved, MISMATCH_FRAMES + 2)
        assert peer.stats[-1]["background"]["state"] == "mismatch"
        assert peer.stats[-1]["background"]["missing_share"] > 0.05
        # `topseg status` shows it while frames come
        sending = threading.Event()

        def keep_sending():
            while not sending.is_set():
                peer.send(noisy(moved, rng))
                time.sleep(0.05)

        feeder = threading.Thread(target=keep_sending)
        feeder.start()
        try:
            r = topseg("status", "--json", "--cell", cell, "--timeout", 2, "--zenoh-port", port, timeout=60)  # fmt: skip
        finally:
            sending.set()
            feeder.join()
        row = json.loads(r.stdout)["cameras"][0]
        assert row["worker"]["background"]["state"] == "mismatch" and r.returncode == 1
        assert any(p.startswith("BACKGROUND MISMATCH: ") for p in row["problems"])
        wait_for(lambda: len(peer.stats) >= peer.seq, 60, "stats of the status frames")
        phase(cell_depth(), MATCH_FRAMES + 2)
        assert peer.stats[-1]["background"]["state"] == "match"
        assert peer.stats[-1]["background"]["mismatches"] == 1
        proc.terminate()
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
        peer.session.close()
    assert proc.returncode == 0, err
    assert err.count("BACKGROUND MISMATCH on bgw/cam0") == 1, err  # said once, not per frame
    assert err.count("matches bgw/cam0 again") == 1, err
    ids = [label.background for label in peer.labels]
    states = [s["background"]["state"] for s in peer.stats]
    # labels say what they were gated with: the background while it matched, none while not
    assert ids[:3] == [bg.id] * 3
    assert all((i is None) == (s == "mismatch") for i, s in zip(ids[1:], states, strict=False))
    assert ids[-1] == bg.id and None in ids


# ---------------------------------------------------------------------------- wire, recordings


def test_labels_carry_the_background_id_and_older_labels_read_without():
    labels = np.zeros((4, 5), np.uint8)
    back = wire.decode_labels(wire.encode_labels(wire.LabelFrame(labels, 3, 4, "cam0", BG_ID)))
    assert back.background == BG_ID
    data = wire.encode_labels(wire.LabelFrame(labels, 3, 4, "cam0"))
    assert "background" not in msgpack.unpackb(data) and wire.decode_labels(data).background is None
    msg = msgpack.unpackb(data)
    msg["v"] = 5  # a version-5 topseg's labels: no background, as before
    assert wire.decode_labels(msgpack.packb(msg)).background is None
    with pytest.raises(wire.WireError, match="unknown"):  # it did not have the field
        wire.decode_labels(msgpack.packb({**msg, "background": BG_ID}))
    for bad in ("AB" * 32, "ab" * 31, 7, "x" * 64):
        with pytest.raises(wire.WireError, match="not a background id"):
            wire.decode_labels(msgpack.packb({**msg, "v": 6, "background": bad}))


def test_stats_carry_the_background_checked():
    good = {"id": BG_ID, "state": "mismatch", "missing_share": 0.1, "mismatch_share": 0.02,
            "sigmas": 3.0, "margin_mm": 10.0, "mismatches": 2}  # fmt: skip
    stats = {"stamp_ns": 1, "timings_ms": {}, "counts": {}, "background": good}
    assert wire.decode_stats(wire.encode_stats(stats))["background"] == good
    for change in ({"state": "maybe"}, {"missing_share": 1.5}, {"id": "x"}, {"mismatches": -1}):
        with pytest.raises(wire.WireError, match="background"):
            wire.encode_stats({**stats, "background": {**good, **change}})


@pytest.mark.parametrize("form", ["msgpack", "ros2"])
def test_both_recordings_keep_what_the_labels_were_gated_with(tmp_path, form):
    path = tmp_path / f"{form}.mcap"
    writer = (recording.RecordingWriter if form == "msgpack" else Ros2RecordingWriter)(path)
    labels = np.zeros((4, 5), np.uint8)
    gated = [None, BG_ID, BG_ID, None, BG_ID]
    with writer:
        for seq, background in enumerate(gated):
            frame = wire.LabelFrame(labels, seq, 10**18 + seq, "cam0", background)
            writer.write(wire.labels_key("c1", "cam0"), wire.encode_labels(frame))
        writer.write(wire.truth_key("c1", "cam0"), wire.encode_labels(wire.LabelFrame(labels, 9)))
    got = [
        wire.decode_labels(m.data).background
        for m in recording.read_messages(path, [wire.labels_key("c1", "cam0")])
    ]
    assert got == gated
    truth = list(recording.read_messages(path, [wire.truth_key("c1", "cam0")]))
    assert wire.decode_labels(truth[0].data).background is None  # ground truth is no one's


def test_status_shows_a_background_that_no_longer_matches():
    seen = status.Observed(alive={("c", "k", "driver"), ("c", "k", "worker")})
    bg = {"id": BG_ID, "state": "match", "missing_share": 0.0, "mismatch_share": 0.02,
          "sigmas": 3.0, "margin_mm": 10.0, "mismatches": 0}  # fmt: skip
    message = {"stamp_ns": 1, "timings_ms": {}, "counts": {"processed": 1}, "background": bg}
    seen.stats[("c", "k")] = [message]
    rep = status.report(seen)
    assert rep["ok"] and status.format_table(rep).splitlines()[1].split()[10] == "on"
    seen.stats[("c", "k")] = [{**message, "background": {**bg, "state": "mismatch", "missing_share": 0.08}}]  # fmt: skip
    rep = status.report(seen)
    assert not rep["ok"] and status.exit_status(rep) == 1
    table = status.format_table(rep)
    assert "MISMATCH" in table.splitlines()[1]
    assert f"c/k: BACKGROUND MISMATCH: 8 % of background {BG_ID[:12]} reads farther" in table
