"""Depth frames over Zenoh on loopback: `topseg bench transport`.

Publishes N wire-encoded 640x480 depth frames (as `topseg driver` does) to a subscriber in
another process (topseg's default loopback config) and reports what arrived, throughput,
and latency from capture stamp to decoded frame. Run it with `--congestion block` and
`--congestion drop`, paced (`--fps 30`) and flat out (`--fps 0`), to see why the driver
publishes depth under BLOCK.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import zenoh

from topseg.core.camera import KINECT_V1
from topseg.core.formats import wire
from topseg.core.metrics import percentile
from topseg.services.cli.options import finite, int_range
from topseg.services.runtime.zenoh_session import open_session


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Frames, rate, Zenoh congestion control and express, and a slow or frozen subscriber."""
    parser.add_argument("--frames", type=int_range(1, 10**7), default=300)
    parser.add_argument(
        "--fps", type=finite(0, 100000), default=30.0, help="publish rate; 0 = flat out"
    )
    parser.add_argument("--congestion", choices=("block", "drop"), default="block")
    parser.add_argument("--no-express", dest="express", action="store_false")
    parser.add_argument(
        "--consumer-ms",
        type=finite(0, 60000),
        default=0.0,
        help="time the subscriber spends on each frame",
    )
    parser.add_argument(
        "--stall-consumer",
        type=finite(0, 3600),
        default=0.0,
        metavar="S",
        help="freeze the subscriber process (SIGSTOP) for S seconds after 1 s",
    )


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _subscriber(port: int, key: str, consumer_ms: float) -> None:
    """Child: receive and decode until 'done', then print counts and latencies as JSON."""
    latencies, seqs, decode_s = [], [], []
    done = threading.Event()

    def on_frame(sample) -> None:
        t0 = time.perf_counter()
        frame = wire.decode_depth(sample.payload.to_bytes())
        decode_s.append(time.perf_counter() - t0)
        latencies.append((time.time_ns() - frame.stamp_ns) / 1e6)
        seqs.append(frame.seq)
        if consumer_ms:
            time.sleep(consumer_ms / 1000)  # a slow consumer, in Zenoh's callback thread

    session = open_session(port=port)
    session.declare_subscriber(key, on_frame)
    session.declare_subscriber(key + "/done", lambda _s: done.set())
    print("ready", flush=True)
    done.wait(120)
    time.sleep(0.3)
    print(json.dumps({"latency_ms": latencies, "seqs": seqs, "decode_s": decode_s}), flush=True)
    session.close()


def measure(args: argparse.Namespace) -> dict:
    """Publish to a subscriber process on a free port: loss, rate, encode/put/decode ms, latency."""
    port = _free_port()
    key = "topseg/bench/cam0/depth"
    child = subprocess.Popen(
        [sys.executable, "-m", __name__, str(port), key, str(args.consumer_ms)],
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    try:
        assert child.stdout.readline().strip() == "ready"
        session = open_session(port=port)
        congestion = {"block": zenoh.CongestionControl.BLOCK, "drop": zenoh.CongestionControl.DROP}
        pub = session.declare_publisher(
            key, congestion_control=congestion[args.congestion], express=args.express
        )
        done = session.declare_publisher(
            key + "/done", congestion_control=zenoh.CongestionControl.BLOCK
        )
        deadline = time.monotonic() + 20
        while not pub.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.05)
        rng = np.random.default_rng(0)
        depth = rng.integers(500, 4000, KINECT_V1.shape, dtype=np.uint16)
        period = 1.0 / args.fps if args.fps > 0 else 0.0
        encode_s, put_s = [], []
        stalled = resumed = False
        t_start = time.perf_counter()
        for i in range(args.frames):
            due = t_start + i * period
            while (left := due - time.perf_counter()) > 0:
                time.sleep(left)
            elapsed = time.perf_counter() - t_start
            if args.stall_consumer and not stalled and elapsed >= 1.0:
                os.kill(child.pid, signal.SIGSTOP)
                stalled = True
            if stalled and not resumed and elapsed >= 1.0 + args.stall_consumer:
                os.kill(child.pid, signal.SIGCONT)
                resumed = True
            t0 = time.perf_counter()
            msg = wire.encode_depth(wire.DepthFrame(depth, KINECT_V1, i, time.time_ns()))
            t1 = time.perf_counter()
            pub.put(msg)
            encode_s.append(t1 - t0)
            put_s.append(time.perf_counter() - t1)
        if stalled and not resumed:
            os.kill(child.pid, signal.SIGCONT)
        send_s = time.perf_counter() - t_start
        done.put(b"done")
        result = json.loads(child.stdout.readline())
        session.close()
    finally:
        child.wait(timeout=30)
    lat = np.array(result["latency_ms"])
    got = len(result["seqs"])
    return {
        "frames_sent": args.frames,
        "frames_received": got,
        "lost_percent": round(100.0 * (args.frames - got) / args.frames, 2),
        "congestion": args.congestion,
        "express": args.express,
        "consumer_ms": args.consumer_ms,
        "publish_fps": round(args.frames / send_s, 1),
        "message_kb": round(len(msg) / 1024, 1),
        "stall_consumer_s": args.stall_consumer,
        "encode_ms_median": round(1000 * float(np.median(encode_s)), 3),
        "put_ms_max": round(1000 * max(put_s), 1),
        "decode_ms_median": round(1000 * float(np.median(result["decode_s"])), 3),
        "latency_ms_p50": round(percentile(lat, 50), 2) if got else None,
        "latency_ms_p99": round(percentile(lat, 99), 2) if got else None,
    }


if __name__ == "__main__":
    _subscriber(int(sys.argv[1]), sys.argv[2], float(sys.argv[3]))
