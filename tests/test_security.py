"""The secure Zenoh setup for real: `topseg router` with deploy/zenoh/secure-router.json5
(TLS, mutual authentication, access control), certificates made by deploy/make-certs.sh,
and clients with the secure-{driver,worker,viewer}.json5 identities, on loopback.

The deploy files are used as written, with only the certificate folder, the port and the
router's host name swapped for the test's. Every "nothing arrives" check has a positive
control: something allowed is sent after the forbidden thing and seen to arrive first.
"""

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh
from netutil import Service, free_port, wait_for

ROOT = Path(__file__).resolve().parent.parent
ZENOH_DIR = ROOT / "deploy" / "zenoh"
MAKE_CERTS = ROOT / "deploy" / "make-certs.sh"


class Secure:
    """The running secure router and a way to open clients of each identity."""

    def __init__(self, tmp: Path) -> None:
        self.tmp, self.port = tmp, free_port()
        self.certs, self.other = tmp / "certs", tmp / "other-ca"
        for d in (self.certs, self.other):
            subprocess.run(["sh", str(MAKE_CERTS), str(d)], check=True, capture_output=True)
        self.sessions: list = []
        self.router = Service("router", "--zenoh-config", self.config("secure-router"))

    def config(self, name: str) -> Path:
        """deploy/zenoh/<name>.json5 with the test's certificate folder, port and host."""
        text = (ZENOH_DIR / f"{name}.json5").read_text()
        text = text.replace("/etc/topseg/certs", str(self.certs))
        text = text.replace(":7447", f":{self.port}").replace("topseg-router.local", "localhost")
        path = self.tmp / f"{name}.json5"
        path.write_text(text)
        return path

    def open(self, role: str, tls: dict | None = None, lenient: bool = False):
        """A session with the secure-<role> config, its TLS block replaced by `tls`.

        As configured (a client) zenoh.open fails when no router takes the link in 3 s;
        `lenient` makes it a peer that opens anyway and keeps trying in the background, to
        check that no data reaches it either."""
        conf = zenoh.Config.from_file(str(self.config(f"secure-{role}")))
        if tls is not None:
            conf.insert_json5("transport/link/tls", json.dumps(tls))
        conf.insert_json5("connect/timeout_ms", "3000")
        if lenient:
            conf.insert_json5("mode", '"peer"')
            conf.insert_json5("listen/endpoints", "[]")
            conf.insert_json5("connect/exit_on_failure", "false")
            conf.insert_json5("connect/timeout_ms", "0")
        session = zenoh.open(conf)
        self.sessions.append(session)
        return session

    def client(self, role: str):
        """A legitimate client, once the router has taken its link."""
        session = self.open(role)
        wait_for(lambda: any(True for _ in session.info.routers_zid()), 10, f"{role} link")
        return session

    def close(self) -> None:
        for s in self.sessions:
            s.close()
        self.router.stop()


@pytest.fixture(scope="module")
def secure(tmp_path_factory):
    s = Secure(tmp_path_factory.mktemp("secure"))
    try:
        s.router.wait_line("listening on", 60)
        yield s
    finally:
        s.close()


def collect(session, key: str) -> list:
    got: list = []
    session.declare_subscriber(key, lambda sample: got.append(sample.payload.to_bytes()))
    return got


def keep_putting(session, key: str, payload: bytes, until, what: str) -> None:
    """Put every 50 ms until `until()` (subscriptions take a moment to reach the router)."""

    def put_and_check():
        session.put(key, payload)
        time.sleep(0.05)
        return until()

    wait_for(put_and_check, 10, what)


def answered_liveliness(session, selector: str) -> bool:
    """Whether a liveliness query from `session` is answered at all (an empty answer too):
    the router has taken what `session` declared before it."""
    list(session.liveliness().get(selector, timeout=1.0))
    return True


def answered(session, selector: str) -> bool:
    """Whether a query from `session` gets an answer."""
    return any(r.ok is not None for r in session.get(selector, timeout=1.0))


def flushed(sender, receiver, key: str) -> None:
    """Return once everything `sender` put or declared before has reached `receiver` (or was
    dropped by the router): a sentinel from the same session on `key`, which `receiver` may
    subscribe to, arrives after them, since one session's messages keep their order through
    the router. A positive signal, instead of a sleep, that a forged message did not come."""
    sentinel = f"sentinel {time.monotonic_ns()}".encode()
    arrived = collect(receiver, key)
    keep_putting(sender, key, sentinel, lambda: sentinel in arrived, f"a sentinel on {key}")


# ---------------------------------------------------------------------------- who connects


def test_client_without_a_certificate_cannot_connect(secure):
    no_cert = {"root_ca_certificate": str(secure.certs / "ca.pem"), "enable_mtls": False}
    with pytest.raises(zenoh.ZError):
        secure.open("viewer", tls=no_cert)
    # A peer opens without a link and keeps trying: it gets no link and no data.
    outsider = secure.open("viewer", tls=no_cert, lenient=True)
    assert_gets_nothing(secure, outsider, "cam-nocert")


@pytest.mark.slow
def test_client_with_a_certificate_from_another_ca_cannot_connect(secure):
    other = {
        "root_ca_certificate": str(secure.certs / "ca.pem"),  # it trusts the real router
        "connect_certificate": str(secure.other / "viewer.pem"),  # CN topseg-viewer, wrong CA
        "connect_private_key": str(secure.other / "viewer-key.pem"),
        "enable_mtls": True,
    }
    with pytest.raises(zenoh.ZError):
        secure.open("viewer", tls=other)
    assert_gets_nothing(secure, secure.open("viewer", tls=other, lenient=True), "cam-otherca")


def test_client_does_not_accept_a_router_from_another_ca(secure):
    fooled = {
        "root_ca_certificate": str(secure.other / "ca.pem"),  # the real router is not its CA's
        "connect_certificate": str(secure.certs / "viewer.pem"),
        "connect_private_key": str(secure.certs / "viewer-key.pem"),
        "enable_mtls": True,
    }
    with pytest.raises(zenoh.ZError):
        secure.open("viewer", tls=fooled)


def test_plain_tcp_cannot_connect(secure):
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{secure.port}"]))
    conf.insert_json5("connect/timeout_ms", "3000")
    conf.insert_json5("scouting/multicast/enabled", "false")
    with pytest.raises(zenoh.ZError):
        zenoh.open(conf).close()


def assert_gets_nothing(secure, outsider, camera: str) -> None:
    """While a real driver publishes depth that a real viewer receives, `outsider` gets none,
    sees no router, no liveliness token and no info reply."""
    key = f"topseg/c/{camera}/depth"
    stolen = collect(outsider, key)
    driver, viewer = secure.client("driver"), secure.client("viewer")
    token = driver.liveliness().declare_token(f"topseg/c/{camera}/alive/driver/d1")
    seen = collect(viewer, key)
    # the outsider reaches no router, so nothing can reach it; the real viewer got depth
    assert not any(True for _ in outsider.info.routers_zid())
    keep_putting(driver, key, b"depth", lambda: len(seen) >= 3, "depth at the real viewer")
    assert stolen == []
    assert [r for r in outsider.liveliness().get("topseg/**", timeout=0.5) if r.ok] == []
    token.undeclare()


# ---------------------------------------------------------------------------- what each role may do


def test_driver_publishes_depth_and_truth_that_worker_and_viewer_receive(secure):
    driver, worker, viewer = (secure.client(r) for r in ("driver", "worker", "viewer"))
    at_worker = collect(worker, "topseg/*/*/depth")
    truth = collect(viewer, "topseg/*/*/truth")
    keep_putting(driver, "topseg/c/d1/depth", b"d", lambda: len(at_worker) >= 3, "depth")
    keep_putting(driver, "topseg/c/d1/truth", b"t", lambda: len(truth) >= 3, "truth")


def test_driver_cannot_publish_labels(secure):
    driver, worker, viewer = (secure.client(r) for r in ("driver", "worker", "viewer"))
    labels = collect(viewer, "topseg/*/*/labels")
    keep_putting(worker, "topseg/c/d2/labels", b"real", lambda: b"real" in labels, "labels")
    for _ in range(5):
        driver.put("topseg/c/d2/labels", b"forged by the driver")
        driver.put("topseg/c/d2/stats", b"forged by the driver")
    flushed(driver, viewer, "topseg/c/d2/depth")
    assert set(labels) == {b"real"}


def test_driver_cannot_subscribe_to_labels_or_depth(secure):
    driver, worker, viewer = (secure.client(r) for r in ("driver", "worker", "viewer"))
    spied_labels = collect(driver, "topseg/*/*/labels")
    spied_depth = collect(driver, "topseg/c/d3/depth")
    labels = collect(viewer, "topseg/*/*/labels")
    depth = collect(viewer, "topseg/c/d3/depth")
    other_driver = secure.client("driver")  # another camera's driver
    keep_putting(worker, "topseg/c/d3/labels", b"l", lambda: len(labels) >= 3, "labels")
    keep_putting(other_driver, "topseg/c/d3/depth", b"d", lambda: len(depth) >= 3, "depth")
    # had the router let the spies subscribe, these would have been routed to the driver
    # too; a token the driver watches, declared after them, arrives after them
    tokens: list = []
    driver.liveliness().declare_subscriber(
        "topseg/c/d3/alive/**", lambda sample: tokens.append(str(sample.key_expr))
    )
    wait_for(lambda: answered_liveliness(driver, "topseg/c/d3/alive/**"), 10, "its watch")
    token = worker.liveliness().declare_token("topseg/c/d3/alive/worker/w3")
    wait_for(lambda: "topseg/c/d3/alive/worker/w3" in tokens, 10, "the worker's token")
    token.undeclare()
    assert spied_labels == [] and spied_depth == []


def test_worker_publishes_labels_and_stats_but_not_depth(secure):
    worker, viewer, other_worker = (secure.client(r) for r in ("worker", "viewer", "worker"))
    labels, stats = collect(viewer, "topseg/*/*/labels"), collect(viewer, "topseg/*/*/stats")
    depth = collect(other_worker, "topseg/*/*/depth")
    flushed(secure.client("driver"), other_worker, "topseg/c/w0/depth")  # its depth route is up
    for _ in range(5):
        worker.put("topseg/c/w1/depth", b"forged by a worker")
    keep_putting(worker, "topseg/c/w1/labels", b"l", lambda: len(labels) >= 3, "labels")
    keep_putting(worker, "topseg/c/w1/stats", b"s", lambda: len(stats) >= 3, "stats")
    flushed(worker, viewer, "topseg/c/w1/labels")  # the router has taken the forged puts
    flushed(secure.client("driver"), other_worker, "topseg/c/w2/depth")  # and delivered them
    assert [d for d in depth if d.startswith(b"forged")] == []


def test_viewer_can_only_listen(secure):
    viewer, worker, viewer2 = (secure.client(r) for r in ("viewer", "worker", "viewer"))
    depth = collect(worker, "topseg/*/*/depth")
    labels = collect(viewer2, "topseg/*/*/labels")
    flushed(secure.client("driver"), worker, "topseg/c/v0/depth")  # the worker's depth route
    keep_putting(worker, "topseg/c/v1/labels", b"real", lambda: b"real" in labels, "labels")
    for _ in range(5):
        viewer.put("topseg/c/v1/depth", b"forged by a viewer")
        viewer.put("topseg/c/v1/labels", b"forged by a viewer")
    # a viewer may put nothing, but may ask a driver's info: the answer proves the router has
    # taken the forged puts before the question; a driver's sentinel, routed after them,
    # then proves that whatever they were routed to has arrived
    driver = secure.client("driver")
    info = driver.declare_queryable("topseg/c/v1/info", lambda q: q.reply(q.key_expr, b"{}"))
    wait_for(lambda: answered(viewer, "topseg/c/v1/info"), 10, "the driver's info")
    info.undeclare()
    depth_at_viewer2 = collect(viewer2, "topseg/c/v1/depth")
    sentinel = b"sentinel"
    keep_putting(
        driver, "topseg/c/v1/depth", sentinel,
        lambda: sentinel in depth and sentinel in depth_at_viewer2, "the driver's sentinel",
    )  # fmt: skip
    assert [d for d in depth if d.startswith(b"forged")] == [] and set(labels) == {b"real"}


def test_roles_hold_only_their_own_liveliness_tokens(secure):
    driver, worker, viewer = (secure.client(r) for r in ("driver", "worker", "viewer"))
    observer = secure.client("viewer")  # a session sees its own tokens: ask from another
    tokens = [
        driver.liveliness().declare_token("topseg/c/t1/alive/driver/d1"),
        driver.liveliness().declare_token("topseg/c/t1/alive/worker/d1"),  # forged
        worker.liveliness().declare_token("topseg/c/t2/alive/worker/w1"),
        worker.liveliness().declare_token("topseg/_any/_any/alive/worker/w1"),
        worker.liveliness().declare_token("topseg/c/t2/alive/driver/w1"),  # forged
        viewer.liveliness().declare_token("topseg/c/t3/alive/driver/v1"),  # forged
    ]

    def alive(session=observer):
        replies = session.liveliness().get("topseg/*/*/alive/**", timeout=1.0)
        return {str(r.ok.key_expr) for r in replies if r.ok is not None}

    expected = {
        "topseg/c/t1/alive/driver/d1",
        "topseg/c/t2/alive/worker/w1",
        "topseg/_any/_any/alive/worker/w1",
    }
    wait_for(lambda: expected <= alive(), 10, "the real tokens")
    for session in (driver, worker, viewer):  # the router has taken every token declared
        answered_liveliness(session, "topseg/**")
    assert {k for k in alive() if "/t" in k or "/_any/" in k} == expected
    # a driver and a worker see the tokens too: one camera, one driver, one worker
    for role in ("driver", "worker"):
        other = secure.client(role)
        wait_for(lambda other=other: expected <= alive(other), 10, f"the tokens, as a {role}")
    for t in tokens:
        t.undeclare()


def test_topseg_status_works_with_the_viewer_identity(secure):
    """`topseg status --zenoh-config secure-viewer.json5` sees the driver's info and both
    roles' tokens and stats through the access control."""
    from topseg.core.formats import wire

    driver, worker = secure.client("driver"), secure.client("worker")
    info = {"role": "driver", "cell": "sec", "camera": "cam0", "source": "synthetic", "frames": 5}
    tokens = [
        driver.liveliness().declare_token(wire.alive_key("sec", "cam0", "driver", "d1")),
        worker.liveliness().declare_token(wire.alive_key("sec", "cam0", "worker", "w1")),
    ]
    queryable = driver.declare_queryable(
        wire.info_key("sec", "cam0"), lambda q: q.reply(q.key_expr, json.dumps(info).encode())
    )
    cmd = [sys.executable, "-m", "topseg.services.cli", "status", "--json", "--cell", "sec"]
    cmd += ["--timeout", "2", "--zenoh-config", str(secure.config("secure-viewer"))]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        stats = {"stamp_ns": 0, "model_id": "m", "fps": 10.0, "counts": {"processed": 1}}
        deadline = time.monotonic() + 30
        while proc.poll() is None and time.monotonic() < deadline:
            stats["stamp_ns"] = time.time_ns()
            stats["timings_ms"] = {"total": 5.0, "latency": 20.0}
            worker.put(wire.stats_key("sec", "cam0"), wire.encode_stats(stats))
            time.sleep(0.1)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
        queryable.undeclare()
        for t in tokens:
            t.undeclare()
    assert proc.returncode == 0, out + err
    cam = json.loads(out)["cameras"][0]
    assert cam["driver"]["alive"] and cam["worker"]["alive"]
    assert cam["driver"]["source"] == "synthetic" and cam["worker"]["model"] == "m"
    assert cam["worker"]["latency_ms"]["p50"] == 20.0


def test_no_role_sends_anything_for_the_reserved_any_camera(secure):
    """`topseg/*/*/depth` matches `_any/_any`, the chunks of a wildcard worker's token: a
    driver certificate could otherwise publish depth there. The
    router denies every message on `topseg/_any/_any/...` but a worker's own token."""
    driver, worker, viewer = (secure.client(r) for r in ("driver", "worker", "viewer"))
    observer = secure.client("viewer")
    depth, truth = collect(worker, "topseg/*/*/depth"), collect(viewer, "topseg/*/*/truth")
    labels, stats = collect(viewer, "topseg/*/*/labels"), collect(viewer, "topseg/*/*/stats")
    forged = b"forged on the reserved pair"
    token = driver.liveliness().declare_token("topseg/_any/_any/alive/driver/d9")
    kept = worker.liveliness().declare_token("topseg/_any/_any/alive/worker/w9")
    for _ in range(5):
        driver.put("topseg/_any/_any/depth", forged)
        driver.put("topseg/_any/_any/truth", forged)
        worker.put("topseg/_any/_any/labels", forged)
        worker.put("topseg/_any/_any/stats", forged)
    keep_putting(driver, "topseg/c/r1/depth", b"real", lambda: b"real" in depth, "depth")
    keep_putting(driver, "topseg/c/r1/truth", b"real", lambda: b"real" in truth, "truth")
    keep_putting(worker, "topseg/c/r1/labels", b"real", lambda: b"real" in labels, "labels")
    keep_putting(worker, "topseg/c/r1/stats", b"real", lambda: b"real" in stats, "stats")

    def alive():
        replies = observer.liveliness().get("topseg/_any/_any/alive/**", timeout=1.0)
        return {str(r.ok.key_expr) for r in replies if r.ok is not None}

    wait_for(lambda: "topseg/_any/_any/alive/worker/w9" in alive(), 10, "the worker's token")
    answered_liveliness(driver, "topseg/**")  # the router has taken the driver's forged token
    # each real message came from the forging session to the same receiver after the forged
    # ones: had the router let one through, it would have arrived first
    assert forged not in depth + truth + labels + stats
    assert alive() == {"topseg/_any/_any/alive/worker/w9"}
    token.undeclare()
    kept.undeclare()
