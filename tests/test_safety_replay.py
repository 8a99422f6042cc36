"""The bundled cell recording through driver -> worker -> safety, each a real process on
loopback Zenoh, read by an independent Zenoh client (plain zenoh and msgpack, none of
topseg's decoders); the decisions scored against the recording's truth."""

import threading
from pathlib import Path

import msgpack
import pytest
import zenoh
from netutil import free_port

from topseg.services.batch.cell_pipeline import run_cell_pipeline

REPO = Path(__file__).resolve().parents[1]
RECORDING = REPO / "recordings" / "cell.mcap"
FIELDS = {"v", "seq", "stamp_ns", "state", "speed_scale", "min_distance_m", "part", "link",
          "reaction_ms", "reasons"}  # fmt: skip


@pytest.mark.slow
def test_the_cell_recording_through_the_services(tmp_path):
    port = free_port()
    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{port}"]')
    config.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
    session = zenoh.open(config)
    seen, lock = [], threading.Lock()

    def on_state(sample):
        msg = msgpack.unpackb(sample.payload.to_bytes(), raw=False)
        with lock:
            seen.append(msg)

    sub = session.declare_subscriber("topseg/default/safety", on_state)
    try:
        figures = run_cell_pipeline(RECORDING, RECORDING.with_suffix(".toml"), port=port,
                                    logs_dir=tmp_path)  # fmt: skip
    finally:
        sub.undeclare()
        session.close()
    assert figures["exit_codes"]["driver"] == 0
    assert figures["background"] == str(RECORDING.with_suffix(".background.npz"))
    with lock:
        states = list(seen)
    assert len(states) > 100
    assert all(FIELDS <= set(m) and m["state"] in ("clear", "warning", "stop") for m in states)
    assert all(m["speed_scale"] == 0.0 for m in states if m["state"] == "stop")
    assert {m["state"] for m in states} >= {"clear", "stop"}  # people come and go
    # the decisions against the truth: never clear when the truth says stop
    assert figures["frames"] > 50  # of 300: a loaded machine drops some
    assert figures["clear_when_truth_stop"] == 0
    assert figures["state_agreement"] > 0.9
