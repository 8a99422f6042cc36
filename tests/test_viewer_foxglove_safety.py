"""`topseg viewer --foxglove --cell` as a real process: a cell's safety state, its zones and
nearest pair as a SceneUpdate and its cameras' placements reach a Foxglove client, decoded
with the schemas the server advertises; and the sink's robot (its capsules as a SceneUpdate,
its silhouette per camera as an image) the same way."""

import threading

import numpy as np
import zenoh
from netutil import Service, free_port
from test_viewer_live import SUBPROTOCOL, FoxgloveClient, stop

from topseg.core.camera import KINECT_V1
from topseg.core.formats import safety_wire, wire
from topseg.core.safety.separation import Capsules
from topseg.services.live.viewer_foxglove import FoxgloveSink
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


def first_served(port: int, topics: list[str], timeout: float) -> tuple[dict, dict]:
    """Connect to the Foxglove server on `port`, wait for `topics`: each one's schema name
    and its first message, decoded."""
    from websockets.sync.client import connect

    with connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL]) as ws:
        client = FoxgloveClient(ws)
        client.wait_for_topics(set(topics), timeout)
        schemas = {t: client.channels[t]["schemaName"] for t in topics}
        return schemas, client.first_messages(topics, timeout)


def test_foxglove_serves_the_safety_state_zones_nearest_pair_and_placements(tmp_path):

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
        topics = ["/topseg/fxs/safety", "/topseg/fxs/safety/scene", "/topseg/fxs/safety/placements"]
        schemas, got = first_served(fport, topics, 90)
        assert schemas[topics[1]] == "foxglove.SceneUpdate"
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


def rotate_z(q) -> np.ndarray:
    """+z turned by the quaternion q (x, y, z, w)."""
    x, y, z, w = q.x, q.y, q.z, q.w
    return np.array([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)])


def test_foxglove_serves_the_robot_silhouette_and_capsules():

    cam, stamp = ("fxs", "cam0"), 10**18 + 123
    k = KINECT_V1.scaled_to(16, 12)
    frame = wire.DepthFrame(np.full(k.shape, 3000, np.uint16), k, 7, stamp, "cam0")
    mask = np.random.default_rng(5).random(k.shape) < 0.3
    a = np.array([[0.2, -0.1, 0.5], [0.2, -0.1, 1.0], [1.0, 1.0, 1.0]])
    b = np.array([[0.2, -0.1, 1.0], [0.6, 0.2, 1.0], [1.0, 1.0, 1.0]])  # the last: a sphere
    radius = np.array([0.1, 0.06, 0.08])
    capsules = Capsules(a, b, radius, ("link1", "link2", "hand"))
    sink = FoxgloveSink.start("127.0.0.1", 0)
    done = threading.Event()

    def log():  # the viewer's logging loop: a silhouette per depth frame, capsules per state
        while not done.is_set():
            sink.silhouette(cam, frame, mask)
            sink.robot("fxs", capsules, stamp)
            done.wait(0.05)

    sink.cameras_changed([cam])
    thread = threading.Thread(target=log, daemon=True)
    thread.start()
    try:
        topics = ["/topseg/fxs/cam0/robot_silhouette", "/topseg/fxs/safety/robot"]
        schemas, got = first_served(sink.server.port, topics, 30)
        assert schemas[topics[0]] == "foxglove.RawImage"
        assert schemas[topics[1]] == "foxglove.SceneUpdate"
    finally:
        done.set()
        thread.join(10)
        sink.close()

    image = got["/topseg/fxs/cam0/robot_silhouette"]
    assert (image.encoding, image.width, image.height, image.step) == ("mono8", 16, 12, 16)
    assert image.frame_id == "fxs_cam0_optical_frame"
    assert image.timestamp.seconds * 10**9 + image.timestamp.nanos == stamp
    pixels = np.frombuffer(image.data, np.uint8).reshape(k.shape)
    np.testing.assert_array_equal(pixels, np.where(mask, 255, 0))

    (entity,) = got["/topseg/fxs/safety/robot"].entities
    assert (entity.id, entity.frame_id) == ("robot", "fxs_floor")
    assert entity.timestamp.seconds * 10**9 + entity.timestamp.nanos == stamp
    # a cylinder between the ends of each capsule that has two, a sphere at each end
    assert len(entity.cylinders) == 2 and len(entity.spheres) == 2 + 2 + 1
    for cylinder, start, end, r in zip(entity.cylinders, a[:2], b[:2], radius[:2], strict=True):
        centre, size = cylinder.pose.position, cylinder.size
        centre = np.array([centre.x, centre.y, centre.z])
        np.testing.assert_allclose(centre, (start + end) / 2)
        length = np.linalg.norm(end - start)
        np.testing.assert_allclose((size.x, size.y, size.z), (2 * r, 2 * r, length))
        axis = rotate_z(cylinder.pose.orientation)  # a cylinder's axis is its local z
        np.testing.assert_allclose(centre + axis * length / 2, end, atol=1e-9)
    balls = entity.spheres
    centres = np.array([(s.pose.position.x, s.pose.position.y, s.pose.position.z) for s in balls])
    np.testing.assert_allclose(centres, [a[0], b[0], a[1], b[1], a[2]])
    diameters = np.array([(s.size.x, s.size.y, s.size.z) for s in balls])
    np.testing.assert_allclose(diameters, np.repeat(2 * radius[[0, 0, 1, 1, 2]], 3).reshape(5, 3))
    colours = {(p.color.r, p.color.g, p.color.b, p.color.a) for p in (*entity.cylinders, *balls)}
    assert len(colours) == 1 and 0.0 < colours.pop()[3] < 1.0  # one colour, see-through
