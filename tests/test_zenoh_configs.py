"""deploy/zenoh/*.json5 parse with Zenoh and say what they should; deploy/make-certs.sh makes
what the secure configs name, with private keys 0600, and is idempotent."""

import json
import stat
import subprocess
from pathlib import Path

import pytest
import zenoh

from topseg.services.runtime import zenoh_session

ROOT = Path(__file__).resolve().parent.parent
ZENOH_DIR = ROOT / "deploy" / "zenoh"
MAKE_CERTS = ROOT / "deploy" / "make-certs.sh"
CONFIGS = sorted(ZENOH_DIR.glob("*.json5"))
ROLES = ("driver", "worker", "viewer")


def get(conf, path):
    return json.loads(conf.get_json(path))


def test_the_expected_configs_are_there():
    names = {p.stem for p in CONFIGS}
    assert names == {"peer", "router", "client", "secure-router"} | {f"secure-{r}" for r in ROLES}
    readme = (ZENOH_DIR / "README.md").read_text()
    assert all(p.name in readme for p in CONFIGS)


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.name)
def test_config_parses(path):
    conf = zenoh.Config.from_file(str(path))
    expected = {"peer": "peer", "router": "router", "secure-router": "router"}
    assert get(conf, "mode") == expected.get(path.stem, "client")
    zenoh_session.make_config(str(path))  # and through topseg's own loader


def test_peer_config_is_topseg_default():
    conf = zenoh.Config.from_file(str(ZENOH_DIR / "peer.json5"))
    for path, value in zenoh_session.default_config_json(zenoh_session.DEFAULT_PORT).items():
        assert get(conf, path) == value, path


def test_secure_configs_are_tls_only_with_mutual_authentication():
    router = zenoh.Config.from_file(str(ZENOH_DIR / "secure-router.json5"))
    assert get(router, "transport/link/protocols") == ["tls"]
    assert all(e.startswith("tls/") for e in get(router, "listen/endpoints"))
    assert get(router, "transport/link/tls/enable_mtls") is True
    acl = get(router, "access_control")
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    assert {cn for s in acl["subjects"] for cn in s["cert_common_names"]} == {
        f"topseg-{r}" for r in ROLES
    }
    rule_ids = {r["id"] for r in acl["rules"]}
    assert all(set(p["rules"]) <= rule_ids for p in acl["policies"])
    for role in ROLES:
        conf = zenoh.Config.from_file(str(ZENOH_DIR / f"secure-{role}.json5"))
        tls = get(conf, "transport/link/tls")
        assert tls["enable_mtls"] and tls["verify_name_on_connect"]
        assert tls["connect_certificate"].endswith(f"/{role}.pem")
        assert all(e.startswith("tls/") for e in get(conf, "connect/endpoints"))


def make_certs(*args):
    return subprocess.run(
        ["sh", str(MAKE_CERTS), *map(str, args)], capture_output=True, text=True, check=True
    ).stdout


def subject_and_san(cert: Path) -> str:
    return subprocess.run(
        ["openssl", "x509", "-in", cert, "-noout", "-subject", "-ext", "subjectAltName"],
        capture_output=True, text=True, check=True,
    ).stdout  # fmt: skip


def test_make_certs_makes_every_file_the_secure_configs_name(tmp_path):
    certs = tmp_path / "certs"
    make_certs(certs, "cellpc.example", "10.1.2.3")
    named = set()
    for path in CONFIGS:
        text = path.read_text()
        named |= {w.split("/")[-1].rstrip('",') for w in text.split() if "/etc/topseg/certs/" in w}
    assert named and all((certs / n).is_file() for n in named), named
    for key in certs.glob("*-key.pem"):
        assert stat.S_IMODE(key.stat().st_mode) == 0o600, key
    router = subject_and_san(certs / "router.pem")
    for name in ("DNS:localhost", "IP Address:127.0.0.1", "DNS:cellpc.example", "10.1.2.3"):
        assert name in router
    for role in ROLES:
        assert f"CN = topseg-{role}" in subject_and_san(certs / f"{role}.pem")
        subprocess.run(
            ["openssl", "verify", "-CAfile", certs / "ca.pem", certs / f"{role}.pem"],
            check=True, capture_output=True,
        )  # fmt: skip


def test_make_certs_keeps_what_exists_and_force_reissues_all_but_the_ca(tmp_path):
    make_certs(tmp_path)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    assert "already holds every certificate" in make_certs(tmp_path)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
    make_certs("--force", tmp_path)
    after = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    assert after["ca.pem"] == before["ca.pem"] and after["ca-key.pem"] == before["ca-key.pem"]
    assert all(after[n] != before[n] for n in after if not n.startswith("ca"))


def test_make_certs_needs_the_ca_key_only_to_issue(tmp_path):
    certs = tmp_path / "certs"
    make_certs(certs)
    (certs / "ca-key.pem").rename(tmp_path / "ca-key.pem")  # kept offline
    assert "already holds every certificate" in make_certs(certs)
    (certs / "worker.pem").unlink()
    done = subprocess.run(["sh", str(MAKE_CERTS), str(certs)], capture_output=True, text=True)
    assert done.returncode == 1 and "ca-key.pem is needed to issue worker.pem" in done.stderr
