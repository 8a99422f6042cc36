"""Disk full while recording, on a real full filesystem: `topseg record` into a 3 MB tmpfs
mounted in a private mount namespace (`unshare -m` as root; else `unshare -rm`, a user
namespace too; skipped where neither is allowed). It stops with one error line and exit
status 2, and the recording up to that point is readable: the bytes read back are the ones
published, and a driver replays it. (tests/test_record.py checks the same under
RLIMIT_FSIZE, which works everywhere.)

In a user namespace Zenoh's shared memory does not reach the recorder: messages over 3 KB
that the publisher puts in /dev/shm never arrive, silently. So there the recorder gets a
config with shared memory off (the publisher then sends over TCP)."""

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
from netutil import Services, Tap, free_port, wait_for
from test_record import Publisher

from topseg.core.camera import KINECT_V1
from topseg.core.formats import recording, wire
from topseg.services.runtime.zenoh_session import default_config_json


def namespace(tmp_path, port: int) -> tuple[list[str], str]:
    """(the `unshare` command prefix, the recorder's Zenoh options), or skip."""
    if shutil.which("unshare") is None:
        pytest.skip("needs unshare(1)")
    if subprocess.run(["unshare", "-m", "true"], capture_output=True).returncode == 0:
        return ["unshare", "-m"], f"--zenoh-port {port}"
    probe = subprocess.run(["unshare", "-rm", "true"], capture_output=True, text=True)
    if probe.returncode != 0:
        pytest.skip(f"mount namespaces unavailable: {probe.stderr.strip()}")
    config = {**default_config_json(port), "transport/shared_memory/enabled": False}
    text = {}
    for path, value in config.items():  # {"a/b": v} -> {"a": {"b": v}}
        *parents, leaf = path.split("/")
        node = text
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = value
    (tmp_path / "no-shm.json5").write_text(json.dumps(text))
    return ["unshare", "-rm"], f"--zenoh-config {tmp_path / 'no-shm.json5'}"


def test_recording_onto_a_full_tmpfs_stops_cleanly_and_replays(tmp_path):
    port, cell = free_port(), "disk1"
    mnt, copy = tmp_path / "small", tmp_path / "copy.mcap"
    mnt.mkdir()
    unshare, zenoh = namespace(tmp_path, port)
    record = f"{sys.executable} -m topseg.services.cli record --out {mnt}/rec.mcap {zenoh}"
    script = (
        f"mount -t tmpfs -o size=3m none {mnt} && {{ {record}; echo rc=$?; "
        f"cp {mnt}/rec.mcap {copy}; ls -A {mnt}; }}"  # the tmpfs goes with the namespace
    )
    proc = subprocess.Popen(
        [*unshare, "sh", "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        start_new_session=True,
    )  # fmt: skip
    pub = Publisher(port, cell)
    key, sent = wire.depth_key(cell), []
    rng = np.random.default_rng(9)
    try:
        pub.wait_matched([key], 60)
        for i in range(12):  # incompressible 600 KB frames: 7 MB into 3 MB
            depth = rng.integers(0, 65536, KINECT_V1.shape, dtype=np.uint16)
            # frame_id = the camera, as drivers send it: the ROS 2 recording gives it back
            frame = wire.DepthFrame(depth, KINECT_V1, i, 10**18 + i, "cam0")
            sent.append(wire.encode_depth(frame))
            pub.pub(key).put(sent[-1])
        out, err = proc.communicate(timeout=60)
    finally:
        pub.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert "rc=2" in out, out + err
    errors = [ln for ln in err.splitlines() if "error" in ln.lower()]
    assert len(errors) == 1 and errors[0].startswith("topseg record: error: "), err
    assert "No space left on device" in errors[0] and "stays readable" in errors[0], err
    assert "Traceback" not in err
    assert out.split("rc=2")[1].split() == ["rec.mcap"], out  # no temp file left behind

    info = recording.RecordingInfo()
    back = [m.data for m in recording.read_messages(copy, info=info)]
    assert 0 < len(back) < len(sent) and info.truncated
    assert back == sent[: len(back)], "what was kept is not what was published"

    # and a driver replays it, every kept frame
    services, port2 = Services(), free_port()
    tap = Tap(port2, cell)
    try:
        drv = services("driver", "--cell", cell, "--source", f"replay:{copy}",
                       "--as-fast-as-possible", "--zenoh-port", port2)  # fmt: skip
        assert drv.proc.wait(60) == 0, drv.err
        wait_for(lambda: len(tap.depth) == len(back), 10, "every kept frame replayed")
        assert [seq for _, seq, _ in tap.depth] == list(range(len(back)))
    finally:
        services.close()
        tap.close()
