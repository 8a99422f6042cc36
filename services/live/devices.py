"""List the depth sensors attached to this machine (Kinect v1, Luxonis OAK), each with the
`--source` spec to give `topseg driver` and, when this user cannot open it, how to fix the
permissions with topseg's udev rules.

Kinect v1 cameras are found on USB with pyusb (045e:02ae); Luxonis OAK devices with pyusb
(03e7:2485 before boot, 03e7:f63b after) and depthai's device list. For each it prints the
`--source` spec to give `topseg driver` and, when the device node is not readable and
writable by this user, how to fix that with topseg's udev rules (`deploy/99-topseg.rules`).
"""

from __future__ import annotations

import argparse
import json
import os
from dataclasses import asdict, dataclass

from topseg.core.extras import needs_extra

KINECT_CAMERA = (0x045E, 0x02AE)
OAK_IDS = {(0x03E7, 0x2485): "unbooted", (0x03E7, 0xF63B): "booted"}
UDEV_HINT = (
    "no permission on {node}: sudo cp deploy/99-topseg.rules /etc/udev/rules.d/ && "
    "sudo udevadm control --reload-rules && sudo udevadm trigger, add yourself to the "
    "plugdev group (sudo usermod -aG plugdev $USER, then log in again) and replug the device"
)


@dataclass
class UsbDevice:
    """What pyusb tells about one USB device of interest."""

    vendor: int
    product: int
    bus: int
    address: int

    @property
    def node(self) -> str:
        """The device's usbfs node, whose permissions decide whether this user may open it."""
        return f"/dev/bus/usb/{self.bus:03d}/{self.address:03d}"


@dataclass
class Sensor:
    """One sensor found: kind, `--source` spec, where it sits, its state, and a fix if needed."""

    kind: str  # "kinect-v1" or "oak"
    spec: str  # what to pass as --source
    usb: str  # bus/address or depthai's protocol
    state: str  # "ready", "no-permission", "booted", ...
    hint: str = ""


def probe_usb() -> tuple[list[UsbDevice], str]:
    """Kinect and OAK devices on USB, and a note when USB cannot be read at all."""
    try:
        import usb.core
    except ImportError:
        return [], needs_extra("devices", "pyusb", "cell")
    wanted = {KINECT_CAMERA, *OAK_IDS}
    try:
        found = usb.core.find(find_all=True)
        devices = [
            UsbDevice(d.idVendor, d.idProduct, d.bus, d.address)
            for d in found
            if (d.idVendor, d.idProduct) in wanted
        ]
    except usb.core.NoBackendError:
        return [], "libusb-1.0 is missing (apt install libusb-1.0-0): cannot list USB devices"
    except (usb.core.USBError, OSError) as exc:
        return [], f"cannot list USB devices: {exc}"
    return devices, ""


def probe_oak() -> tuple[list[dict], str]:
    """OAK devices as depthai sees them (id, name, state)."""
    try:
        from topseg.drivers import SourceError
        from topseg.drivers.oak import import_depthai

        dai = import_depthai()
        infos = dai.Device.getAllAvailableDevices()
    except SourceError as exc:  # depthai is not installed, or cannot load
        return [], str(exc)
    except Exception as exc:  # a missing or broken depthai only hides OAK devices
        return [], f"depthai cannot list devices: {exc}"
    return [
        {"id": i.getDeviceId(), "name": i.name, "state": str(i.state).rsplit(".", 1)[-1]}
        for i in infos
    ], ""


def describe(
    usb_devices: list[UsbDevice], oak_devices: list[dict], can_access=None
) -> list[Sensor]:
    """Sensors with their spec, state and, when needed, what to do (pure but for access)."""
    can_access = can_access or (lambda node: os.access(node, os.R_OK | os.W_OK))
    sensors = []
    kinects = [d for d in usb_devices if (d.vendor, d.product) == KINECT_CAMERA]
    for index, dev in enumerate(sorted(kinects, key=lambda d: (d.bus, d.address))):
        ok = can_access(dev.node)
        sensors.append(
            Sensor(
                "kinect-v1",
                f"freenect:{index}",
                f"usb {dev.bus:03d}/{dev.address:03d}",
                "ready" if ok else "no-permission",
                "" if ok else UDEV_HINT.format(node=dev.node),
            )
        )
    listed = {d["id"] for d in oak_devices}
    for info in oak_devices:
        sensors.append(Sensor("oak", f"oak:{info['id']}", info["name"], info["state"].lower()))
    for dev in usb_devices:
        state = OAK_IDS.get((dev.vendor, dev.product))
        if state is None or listed:
            continue  # depthai listed them already (with ids)
        if can_access(dev.node):
            hint = "depthai does not list it: is another process using it?"
        else:
            hint = UDEV_HINT.format(node=dev.node)
        sensors.append(Sensor("oak", "oak", f"usb {dev.bus:03d}/{dev.address:03d}", state, hint))
    return sensors


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """`topseg devices` options: JSON output, and skipping depthai (slow to load, may be absent)."""
    parser.add_argument("--json", action="store_true", help="print a JSON object")
    parser.add_argument("--no-depthai", action="store_true", help="do not ask depthai for OAKs")


def run(args: argparse.Namespace) -> int:
    """Print the sensors found (a table or JSON) with the notes of probes that failed; always 0."""
    usb_devices, usb_note = probe_usb()
    oak_devices, oak_note = ([], "") if args.no_depthai else probe_oak()
    sensors = describe(usb_devices, oak_devices)
    notes = [n for n in (usb_note, oak_note) if n]
    if args.json:
        print(json.dumps({"sensors": [asdict(s) for s in sensors], "notes": notes}, indent=2))
        return 0
    if not sensors:
        print("no depth sensors found (Kinect v1 045e:02ae, OAK 03e7:2485/f63b)")
    for s in sensors:
        print(f"{s.kind:<10} {s.spec:<28} {s.usb:<16} {s.state}")
        if s.hint:
            print(f"  -> {s.hint}")
    for note in notes:
        print(f"note: {note}")
    return 0
