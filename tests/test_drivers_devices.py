"""`topseg devices`: what it says about sensors, and the udev rules it points to."""

import json
import re
import subprocess
import sys
from pathlib import Path

from topseg.services.live import devices
from topseg.services.live.devices import UsbDevice

RULES = Path(__file__).parents[1] / "deploy" / "99-topseg.rules"


def test_kinects_get_specs_in_bus_order_and_a_permission_hint():
    usb = [
        UsbDevice(0x045E, 0x02AE, 3, 9),
        UsbDevice(0x045E, 0x02AE, 1, 4),
        UsbDevice(0x1234, 1, 1, 1),
    ]
    denied = {"/dev/bus/usb/003/009"}
    sensors = devices.describe(usb, [], can_access=lambda node: node not in denied)
    assert [(s.kind, s.spec, s.state) for s in sensors] == [
        ("kinect-v1", "freenect:0", "ready"),
        ("kinect-v1", "freenect:1", "no-permission"),
    ]
    assert sensors[0].hint == ""
    assert "/dev/bus/usb/003/009" in sensors[1].hint and "99-topseg.rules" in sensors[1].hint


def test_oak_devices_from_depthai_or_usb():
    listed = [{"id": "14442C10D13EABCE00", "name": "1.3", "state": "UNBOOTED"}]
    sensors = devices.describe([UsbDevice(0x03E7, 0x2485, 1, 2)], listed, can_access=lambda n: True)
    assert [(s.spec, s.state) for s in sensors] == [("oak:14442C10D13EABCE00", "unbooted")]
    # seen on USB but not by depthai: no permission, or held by another process
    sensors = devices.describe([UsbDevice(0x03E7, 0xF63B, 1, 2)], [], can_access=lambda n: False)
    assert sensors[0].state == "booted" and "udev" in sensors[0].hint


def test_udev_rules_cover_every_device_topseg_lists():
    rules = RULES.read_text()
    ids = set(re.findall(r'ATTR\{idVendor\}=="(\w{4})", ATTR\{idProduct\}=="(\w{4})"', rules))
    wanted = {devices.KINECT_CAMERA, *devices.OAK_IDS}
    assert {(f"{v:04x}", f"{p:04x}") for v, p in wanted} <= ids
    for line in rules.splitlines():
        if line and not line.startswith("#"):
            assert (
                'SUBSYSTEM=="usb"' in line and 'MODE="0660"' in line and 'GROUP="plugdev"' in line
            )


def test_devices_command_runs_here():
    cmd = [sys.executable, "-m", "topseg.services.cli", "devices", "--json", "--no-depthai"]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout)
    assert set(report) == {"sensors", "notes"}
    for sensor in report["sensors"]:
        assert sensor["spec"].split(":")[0] in ("freenect", "oak")
