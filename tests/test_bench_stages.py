"""`topseg bench stages` as a real process on the bundled cell recording and on small
recordings written here: every stage's figures, the loop over a short recording, and the
refusals."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from topseg.core.formats import wire
from topseg.core.formats.recording import RecordingWriter, read_messages
from topseg.core.segmenter import Segmenter

CELL = Path(__file__).resolve().parents[1] / "recordings" / "cell.mcap"


def bench(*args):
    cmd = [sys.executable, "-m", "topseg.services.cli", "bench", "stages", "--json", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300)


def first_depth(count):
    """The first `count` depth messages of the bundled cell recording, as recorded."""
    out = []
    for m in read_messages(CELL):
        if m.key.endswith("/depth"):
            out.append(m)
            if len(out) == count:
                return out
    raise AssertionError("the cell recording has too few depth frames")


@pytest.mark.slow
def test_every_stage_of_the_cell_recording_is_timed():
    done = bench("--frames", "3", "--warmup", "1")
    assert done.returncode == 0, done.stderr
    figures = json.loads(done.stdout)
    assert figures["frames"] == 3 and figures["frame_size"] == "320x240"
    assert figures["background"] is True  # the recording's own, beside it
    stages = Segmenter.from_file(None).stage_names
    for name in (*stages, "total"):
        p50, p90, p99 = (figures[f"{name}_ms_p{q}"] for q in (50, 90, 99))
        assert 0 <= p50 <= p90 <= p99, name
    assert figures["total_ms_p99"] >= max(figures[f"{n}_ms_p99"] for n in stages)
    assert figures["forest_ms_p50"] > 0 and figures["crf_ms_p50"] > 0
    assert figures["wall_ms_per_frame"] > 0 and figures["cpu_ms_per_frame"] > 0
    assert bench("--frames", "1", "--warmup", "0", "--no-background").returncode == 0


@pytest.mark.slow
def test_a_short_recording_loops_and_damaged_frames_are_skipped(tmp_path):
    short = tmp_path / "short.mcap"
    messages = first_depth(2)
    with RecordingWriter(short) as w:
        for i, m in enumerate(messages):
            w.write(m.key, m.data, 10**18 + i)
        w.write(messages[0].key, b"\xc1 not a depth frame", 10**18 + 5)
    done = bench("--recording", str(short), "--frames", "5", "--warmup", "0", "--no-background")
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["frames"] == 5


@pytest.mark.slow
def test_a_recording_without_depth_or_none_at_all_is_refused(tmp_path):
    stats_only = tmp_path / "stats.mcap"
    with RecordingWriter(stats_only) as w:
        w.write(wire.stats_key("c1"), wire.encode_stats({"stamp_ns": 1, "timings_ms": {},
                                                         "counts": {}}), 1)  # fmt: skip
    done = bench("--recording", str(stats_only), "--frames", "2")
    assert done.returncode != 0 and "holds no depth channel" in done.stderr  # the replay reader's
    assert "Traceback" not in done.stderr
    damaged = tmp_path / "damaged.mcap"
    with RecordingWriter(damaged) as w:
        w.write(first_depth(1)[0].key, b"\xc1 not a depth frame", 1)
    done = bench("--recording", str(damaged), "--frames", "2")
    assert done.returncode != 0 and "no depth frames to label" in done.stderr
    assert "Traceback" not in done.stderr
    done = bench("--recording", str(tmp_path / "missing.mcap"))
    assert done.returncode != 0 and "no such recording" in done.stderr
