"""`topseg viewer --foxglove --cell` as a real process: a cell's safety state, its zones and
nearest pair as a SceneUpdate and its cameras' placements reach a Foxglove client, decoded
with the schemas the server advertises."""

import threading

import numpy as np
import zenoh
from netutil import Service, free_port
from test_viewer_live import SUBPROTOCOL, FoxgloveClient, stop

from topseg.core.formats import safety_wire
from topseg.services.runtime.zenoh_session import open_session

CELL_TOML = """
cell = "fxs"
[[camera]]
name = "cam0"
x_m = 1.0
yaw_deg = 90.0
[[zone]]
name = "guard"
kind = "warning"
polygon_m = [[-1.4, -1.0], [-0.8, -1.0], [-0.8, -0.4]]
"""
STOP = (220 / 255, 30 / 255, 30 / 255)


def test_foxglove_serves_the_safety_state_zones_nearest_pair_and_placements(tmp_path):
    from websockets.sync.client import connect

    cell_file = tmp_path / "cell.toml"
    cell_file.write_text(CELL_TOML)
    zport, fport = free_port(), free_port()
    viewer = Service(
        "viewer", "--foxglove", "--foxglove-port", fport, "--cell", cell_file,
        "--zenoh-port", zport,
    )  # fmt: skip
    session, done = open_session(port=zport), threading.Event()
    state = safety_wire.SafetyState(
        seq=3, stamp_ns=10**18, state="stop", speed_scale=0.0, min_distance_m=0.3,
        part="hand", link="link7", reaction_ms=45.0, reasons=("hand in zone guard",),
        zones={"guard": "stop"}, nearest_m=((0.0, 0.0, 1.0), (0.3, 0.0, 1.0)),
    )  # fmt: skip
    pub = session.declare_publisher(
        safety_wire.safety_key("fxs"), congestion_control=zenoh.CongestionControl.BLOCK
    )

    def publish():
        while not done.is_set():
            pub.put(safety_wire.encode_safety(state))
            done.wait(0.1)

    thread = threading.Thread(target=publish, daemon=True)
    try:
        viewer.wait_line("viewer ready")
        thread.start()
        with connect(f"ws://127.0.0.1:{fport}", subprotocols=[SUBPROTOCOL]) as ws:
            client = FoxgloveClient(ws)
            topics = [
                "/topseg/fxs/safety",
                "/topseg/fxs/safety/scene",
                "/topseg/fxs/safety/placements",
            ]
            client.wait_for_topics(set(topics), 90)
            assert client.channels[topics[1]]["schemaName"] == "foxglove.SceneUpdate"
            got = client.first_messages(topics, 90)
    finally:
        done.set()
        thread.join(10)
        session.close()
        code = stop(viewer) if viewer.alive() else viewer.proc.returncode
    assert code == 0, viewer.err

    json_state = got["/topseg/fxs/safety"]
    assert (json_state["state"], json_state["level"], json_state["speed_scale"]) == ("stop", 2, 0.0)
    assert json_state["reasons"] == ["hand in zone guard"] and json_state["zones"] == {
        "guard": "stop"
    }

    scene = got["/topseg/fxs/safety/scene"]
    entities = {e.id: e for e in scene.entities}
    assert {e.frame_id for e in entities.values()} == {"fxs_floor"}
    zone = entities["zone/guard"]
    assert len(zone.lines) == 2 + 3  # outline at z_min and z_max, three vertical edges
    bottom = [(p.x, p.y, p.z) for p in zone.lines[0].points]
    assert bottom == [(-1.4, -1.0, 0.0), (-0.8, -1.0, 0.0), (-0.8, -0.4, 0.0), (-1.4, -1.0, 0.0)]
    colour = zone.lines[0].color
    np.testing.assert_allclose((colour.r, colour.g, colour.b), STOP, atol=1e-6)
    nearest = entities["nearest"]
    assert [(p.x, p.y, p.z) for p in nearest.lines[0].points] == [(0, 0, 1.0), (0.3, 0, 1.0)]
    assert nearest.texts[0].text == "0.30 m"

    (placement,) = got["/topseg/fxs/safety/placements"].transforms
    assert (placement.parent_frame_id, placement.child_frame_id) == ("fxs_floor", "fxs_cam0_floor")
    assert (placement.translation.x, placement.translation.y) == (1.0, 0.0)
    np.testing.assert_allclose(
        (placement.rotation.z, placement.rotation.w), (np.sqrt(0.5), np.sqrt(0.5))
    )
