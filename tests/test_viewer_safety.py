"""The viewer's safety view: `topseg viewer --save --cell` as a real process on loopback
Zenoh, fed safety states and joint states; the .rrd is read back with Rerun's CLI."""

import signal
import subprocess
import sys
import threading
import time

import numpy as np
import zenoh
from netutil import free_port

from topseg.core.camera import KINECT_V1, TopViewMount
from topseg.core.formats import joint_states, safety_wire, wire
from topseg.core.safety.cell import CameraPlacement, Zone
from topseg.core.safety.separation import Capsules
from topseg.services.live import safety_view
from topseg.services.runtime.zenoh_session import open_session

CELL_TOML = """
cell = "vsafe"
[robot]
name = "arm"
urdf = "panda"
base_xyz_m = [0.5, 0.0, 0.0]
[[camera]]
name = "cam0"
x_m = 1.0
yaw_deg = 90.0
[[zone]]
name = "guard"
kind = "protective"
polygon_m = [[-1.4, -1.0], [-0.8, -1.0], [-0.8, -0.4], [-1.4, -0.4]]
"""
PANDA_JOINTS = [f"panda_joint{i}" for i in range(1, 8)] + ["panda_finger_joint1"]


def rrd_chunks(path) -> dict[str, str]:
    """`rerun rrd print -vvv`, the text of every chunk by entity path."""
    out = subprocess.run(
        [sys.executable, "-m", "rerun", "rrd", "print", "-vvv", str(path)],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    chunks: dict[str, str] = {}
    for block in out.stdout.split("Chunk(")[1:]:
        entity = block.split("\n", 1)[0].split(" - ")[1].strip()
        chunks[entity] = chunks.get(entity, "") + block
    return chunks


def packed(rgb) -> str:
    """A colour as Rerun prints it: 0xRRGGBBAA as an integer."""
    return str(int.from_bytes(bytes([*rgb, 255]), "big"))


def test_zone_outlines_are_drawn_in_the_cameras_world_frame():
    zone = Zone("z", "warning", ((0.0, 0.0), (1.0, 0.0), (1.0, 2.0)), z_min_m=0.1, z_max_m=2.0)
    placement = CameraPlacement("cam0", x_m=1.0, y_m=0.5, yaw_deg=90.0)
    strips = safety_view.zone_strips(zone, placement)
    assert len(strips) == 2 + 3  # bottom, top, one vertical per vertex
    bottom, top = strips[0], strips[1]
    assert len(bottom) == 4 and np.allclose(bottom[0], bottom[-1])  # closed
    assert np.allclose(bottom[:, 2], 0.1) and np.allclose(top[:, 2], 2.0)
    # the cell's (0, 0) seen from a camera at (1, 0.5) turned by 90 degrees
    assert np.allclose(bottom[0], [-0.5, 1.0, 0.1])
    assert np.allclose(placement.to_cell(bottom[:-1])[:, :2], zone.polygon_m)


def test_capsules_are_posed_along_their_axes():
    a = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.0, 0.0, 1.0], [2.0, 0.0, 0.0]])
    b = np.array([[0.0, 0.0, 1.0], [1.0, 2.0, 1.0], [0.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    posed = safety_view.posed_capsules(Capsules(a, b, np.full(4, 0.1), ("l0", "l1", "l2", "s")))
    assert np.allclose(posed.length, [1.0, 1.0, 1.0, 0.0])
    for q, start, end, length in zip(posed.quaternion, a, b, posed.length, strict=True):
        x, y, z, w = q
        # the rotation of +z by q
        tip = np.array([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)])
        assert np.isclose(np.linalg.norm(q), 1.0)
        if length > 0:
            assert np.allclose(start + tip * length, end)


def test_viewer_shows_states_zones_nearest_pair_and_robot(tmp_path):
    cell_file, rrd, port = tmp_path / "cell.toml", tmp_path / "safety.rrd", free_port()
    cell_file.write_text(CELL_TOML)
    session = open_session(port=port)
    cmd = [sys.executable, "-m", "topseg.services.cli", "-v", "viewer", "--save", str(rrd)]
    proc = subprocess.Popen(
        [*cmd, "--cell", str(cell_file), "--zenoh-port", str(port)],
        stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stderr))
    reader.start()
    try:
        block = dict(congestion_control=zenoh.CongestionControl.BLOCK)
        safety = session.declare_publisher(safety_wire.safety_key("vsafe"), **block)
        other = session.declare_publisher(safety_wire.safety_key("vfree"), **block)
        joints = session.declare_publisher(joint_states.joints_key("vsafe", "arm"), **block)
        depth = session.declare_publisher(wire.depth_key("vsafe", "cam0"), **block)
        mount = TopViewMount(KINECT_V1.scaled_to(160, 120), 3000.0)
        floor = np.full((120, 160), 3000, np.uint16)
        stop = safety_wire.SafetyState(
            seq=0, stamp_ns=10**18, state="stop", speed_scale=0.0, min_distance_m=0.4,
            part="hand", link="panda_link7", reaction_ms=42.0, reasons=("hand in zone guard",),
            zones={"guard": "stop"}, nearest_m=((1.0, 0.0, 1.0), (1.4, 0.0, 1.0)),
            frame=("cam0", 7),
        )  # fmt: skip
        free = safety_wire.SafetyState(
            seq=0, stamp_ns=10**18, state="warning", speed_scale=0.5, min_distance_m=1.25,
            nearest_m=((0.0, 0.0, 1.0), (1.25, 0.0, 1.0)), reasons=("person near",),
        )  # fmt: skip
        pose = joint_states.JointState(10**18, tuple(PANDA_JOINTS), (0.0,) * len(PANDA_JOINTS))
        wanted = [
            "logging vsafe/safety",
            "logging vfree/safety",
            "logging vsafe/robot",
            "logging vsafe/cam0/robot silhouette",
            "rejected)",
        ]
        seq = 0
        deadline = time.monotonic() + 90
        while not all(w in "".join(lines) for w in wanted):
            assert time.monotonic() < deadline, f"viewer never logged {wanted}: {''.join(lines)}"
            assert proc.poll() is None, "".join(lines)
            safety.put(safety_wire.encode_safety(stop))
            other.put(safety_wire.encode_safety(free))
            joints.put(joint_states.encode_joint_state(pose))
            seq += 1
            depth.put(
                wire.encode_depth(
                    wire.DepthFrame(floor, mount.intrinsics, seq, 10**18, "cam0", mount)
                )
            )
            safety.put(b"\x81\xa1v\x02")  # a map of the wrong version: rejected, counted
            time.sleep(1)
        proc.send_signal(signal.SIGTERM)
        reader.join(timeout=30)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
        session.close()
    assert proc.returncode == 0, "".join(lines)
    chunks = rrd_chunks(rrd)
    for entity, archetype in [
        ("/vsafe/safety/state", "Scalars"),
        ("/vsafe/safety/speed_scale", "Scalars"),
        ("/vsafe/safety/reaction_ms", "Scalars"),
        ("/vsafe/safety/min_distance_m", "Scalars"),
        ("/vsafe/safety/reasons", "TextLog"),
        ("/world/vsafe/cam0/safety/zones/guard", "LineStrips3D"),
        ("/world/vsafe/cam0/safety/nearest", "LineStrips3D"),
        ("/world/vsafe/cam0/safety/robot", "Capsules3D"),
        ("/world/vsafe/cam0/camera/image/robot_silhouette", "SegmentationImage"),
        ("/vfree/safety/state", "Scalars"),
        ("/world/vfree/safety/nearest", "LineStrips3D"),  # no cell file: the cell frame
    ]:
        assert f"{archetype}:" in chunks.get(entity, ""), f"{entity} {archetype} missing"
    guard = chunks["/world/vsafe/cam0/safety/zones/guard"]
    # grey before the first state, then red: the zone's state is stop
    assert packed(safety_view.UNKNOWN_COLOUR) in guard
    assert packed(safety_view.STATE_COLOURS["stop"]) in guard
    # the cell's (-1.4, -1.0) seen from cam0 at (1, 0) turned by 90 degrees: (-1.0, 2.4)
    assert "[-1.0, 2.4, 0.0]" in guard
    nearest = chunks["/world/vsafe/cam0/safety/nearest"]
    # the robot's end (1.4, 0, 1) of the pair in cam0's frame: (0, -0.4, 1)
    assert "0.40 m" in nearest and "-0.4, 1.0]" in nearest
    assert "1.25 m" in chunks["/world/vfree/safety/nearest"]
    assert "stop: hand in zone guard" in chunks["/vsafe/safety/reasons"]
    assert "panda_link" in chunks["/world/vsafe/cam0/safety/robot"]
