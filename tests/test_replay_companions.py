"""A replay publishes a recording's joint states and safety truth with the depth frames they
were recorded with: `topseg driver --source replay:FILE.mcap` as a real process on loopback
Zenoh, and the readers underneath it."""

import msgpack
import numpy as np
import pytest
from netutil import free_port, wait_for
from test_driver_service import start_driver, stop

from topseg.core.camera import KINECT_V1
from topseg.core.formats import cell_truth, wire
from topseg.core.formats.recording import RecordingWriter
from topseg.drivers.replay import RecordingFrames
from topseg.services.runtime.zenoh_session import open_session

K = KINECT_V1.scaled_to(160, 120)
N = 5
PERIOD_NS = 100_000_000  # 10 fps
#: joint states per frame, this far apart (ns) after the frame
JOINT_OFFSETS_NS = (0, 30_000_000, 60_000_000)
T0 = 1_000_000_000_000


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """N frames from cell "rec": depth, truth, three joint states each (positions[0] names the
    frame and the state: i + k / 10) and a safety truth; one joint state before the first
    frame (20 ms before it)."""
    path = tmp_path_factory.mktemp("rec") / "cell.mcap"
    joints = cell_truth.joints_key("rec", "panda")
    with RecordingWriter(path) as w:
        w.write(joints, cell_truth.encode_joint_state(T0 - 20_000_000, ["j1"], [-1.0]), T0 - 1)
        for i in range(N):
            t = T0 + i * PERIOD_NS
            depth = np.full(K.shape, 2500 + i, np.uint16)
            w.write(wire.depth_key("rec"), wire.encode_depth(wire.DepthFrame(depth, K, i, t)), t)
            labels = np.zeros(K.shape, np.uint8)
            w.write(wire.truth_key("rec"), wire.encode_labels(wire.LabelFrame(labels, i, t)), t)
            for k, off in enumerate(JOINT_OFFSETS_NS):
                state = cell_truth.encode_joint_state(t + off, ["j1"], [i + k / 10])
                w.write(joints, state, t + off)
            person = {"id": 0, "distance_m": 0.1 * i}
            truth = cell_truth.encode_safety_truth(t, i, [person])
            w.write(cell_truth.safety_truth_key("rec"), truth, t + 1)
    return path


def test_the_reader_hands_each_frame_its_companions_with_their_offsets(recording):
    frames = list(RecordingFrames(recording, companions=True))
    assert len(frames) == N
    first = [(c.key.rsplit("/", 1)[-1], c.offset_ns) for c in frames[0].companions]
    assert first[0] == ("joints", -20_000_000)
    for i, f in enumerate(frames):
        joints = [c for c in f.companions if c.key.endswith("/joints")]
        assert [c.offset_ns for c in joints][-3:] == list(JOINT_OFFSETS_NS)
        positions = [msgpack.unpackb(c.data)["position"][0] for c in joints][-3:]
        assert positions == pytest.approx([i, i + 0.1, i + 0.2])
        (safety,) = [c for c in f.companions if c.key.endswith("/safety/separation")]
        assert msgpack.unpackb(safety.data)["seq"] == i
    # without companions (what `topseg segment` reads) nothing changes
    assert all(not f.companions for f in RecordingFrames(recording))


def test_replay_publishes_joint_states_in_step_with_their_depth_frames(recording):
    port, cell = free_port(), "svcj"
    session = open_session(port=port)
    depth, joints, safety = [], [], []
    session.declare_subscriber(wire.depth_key(cell), lambda s: depth.append(s.payload.to_bytes()))
    session.declare_subscriber(
        cell_truth.joints_key(cell, "panda"), lambda s: joints.append(s.payload.to_bytes())
    )
    session.declare_subscriber(
        cell_truth.safety_truth_key(cell), lambda s: safety.append(s.payload.to_bytes())
    )
    proc = start_driver(port, cell, "--source", f"replay:{recording}", "--loop")
    try:
        wait_for(lambda: len(safety) >= 2 * N + 2, what="two passes of safety truth")
        rc, err = stop(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
        session.close()
    assert rc == 0, err
    frames = [wire.decode_depth(b) for b in depth]
    stamp_of = {f.seq: f.stamp_ns for f in frames}
    states = [msgpack.unpackb(b) for b in joints]
    assert states and all(s["name"] == ["j1"] for s in states)
    matched = 0
    for s in states:
        code = s["position"][0]
        if code < 0:  # recorded before the first frame: goes with it, 20 ms before it
            firsts = [f.stamp_ns for f in frames if f.seq % N == 0]
            assert any(s["stamp_ns"] == t - 20_000_000 for t in firsts)
            continue
        index, k = divmod(round(code * 10), 10)
        mine = [f.stamp_ns for f in frames if f.seq % N == index]
        gaps = [s["stamp_ns"] - t for t in mine]
        assert JOINT_OFFSETS_NS[k] in gaps, (s, mine)  # restamped like its frame
        assert 0 <= JOINT_OFFSETS_NS[k] < PERIOD_NS
        matched += 1
    assert matched >= 2 * N * len(JOINT_OFFSETS_NS) - len(JOINT_OFFSETS_NS)
    for t in map(msgpack.unpackb, safety):
        if t["seq"] in stamp_of:
            assert t["stamp_ns"] == stamp_of[t["seq"]]
            assert t["persons"][0]["distance_m"] == pytest.approx(0.1 * (t["seq"] % N))
