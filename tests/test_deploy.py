"""deploy/: the systemd units pass `systemd-analyze verify`, keep the settings the services
rely on (notify, watchdog, one user for shared memory, USB for the driver), start with the
example configs, and the udev rules give sensors to a group without making them world-writable."""

from __future__ import annotations

import hashlib
import json
import re
import shlex
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
from netutil import Services, free_port

from topseg.services import cli

ROOT = Path(__file__).resolve().parent.parent
DEPLOY = ROOT / "deploy"
UNITS = DEPLOY / "systemd"
CONFIGS = DEPLOY / "config"
INSTALLED_TOPSEG = "/opt/topseg/venv/bin/topseg"
#: unit file -> the instance its example config is for ("" for plain units)
UNIT_INSTANCES = {
    "topseg-driver@.service": ["kinect", "oak", "demo"],
    "topseg-worker@.service": ["kinect", "oak", "demo", "worker"],
    "topseg-viewer.service": [""],
    "topseg-router.service": [""],
    "topseg-bridge-ros2.service": [""],
    "topseg-safety@.service": ["cell1"],
}
SYSTEMD_ANALYZE = shutil.which("systemd-analyze") or (
    "/usr/bin/systemd-analyze" if Path("/usr/bin/systemd-analyze").exists() else None
)
needs_analyze = pytest.mark.skipif(
    SYSTEMD_ANALYZE is None, reason="systemd-analyze is not installed (Debian: systemd)"
)


def parse_unit(path: Path) -> dict[str, list[tuple[str, str]]]:
    """{section: [(key, value), ...]} of a unit file (keys may repeat, as systemd allows)."""
    sections: dict[str, list[tuple[str, str]]] = {}
    current = None
    for line in path.read_text().splitlines():
        line = line.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("["):
            current = line.strip("[]")
            sections.setdefault(current, [])
            continue
        key, _, value = line.partition("=")
        sections[current].append((key.strip(), value.strip()))
    return sections


def values(unit: dict, section: str, key: str) -> list[str]:
    return [v for k, v in unit.get(section, []) if k == key]


def value(unit: dict, section: str, key: str) -> str | None:
    found = values(unit, section, key)
    return found[-1] if found else None


def local_topseg() -> Path:
    """The topseg entry point of the venv running the tests (stands in for /opt/topseg's)."""
    path = Path(sys.executable).parent / "topseg"
    if not path.exists():
        pytest.skip(f"no topseg entry point next to {sys.executable}")
    return path


def test_units_exist():
    assert sorted(p.name for p in UNITS.glob("*.service")) == sorted(UNIT_INSTANCES)


@needs_analyze
@pytest.mark.parametrize("name", sorted(UNIT_INSTANCES))
def test_systemd_analyze_verify(name, tmp_path):
    """Each unit (and one instance of a template) verifies with no warning at all.

    `verify` checks that ExecStart's program exists, so the copy points at this venv's topseg.
    """
    text = (UNITS / name).read_text()
    assert INSTALLED_TOPSEG in text
    text = text.replace(INSTALLED_TOPSEG, str(local_topseg()))
    files = [tmp_path / name]
    if "@." in name:
        files.append(tmp_path / name.replace("@.", "@kinect."))
    for f in files:
        f.write_text(text)
    result = subprocess.run(
        [SYSTEMD_ANALYZE, "verify", *map(str, files)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    output = (result.stdout + result.stderr).strip()
    assert result.returncode == 0, output
    assert output == "", f"systemd-analyze verify warned:\n{output}"


@needs_analyze
@pytest.mark.parametrize("name", sorted(UNIT_INSTANCES))
def test_systemd_analyze_security(name, tmp_path):
    """The hardening keeps the exposure score `OK` (below 2.0 of 10)."""
    unit = tmp_path / name
    unit.write_text((UNITS / name).read_text().replace(INSTALLED_TOPSEG, str(local_topseg())))
    result = subprocess.run(
        [SYSTEMD_ANALYZE, "security", "--offline=true", "--no-pager", str(unit)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    m = re.search(r"Overall exposure level for \S+: (\d+\.\d+)", result.stdout + result.stderr)
    if m is None and "--offline" in result.stderr:
        pytest.skip("this systemd-analyze has no --offline (systemd < 250)")
    assert m, result.stdout + result.stderr
    assert float(m[1]) < 2.0, result.stdout


@pytest.mark.parametrize("name", sorted(UNIT_INSTANCES))
def test_unit_settings(name):
    unit = parse_unit(UNITS / name)
    service = "Service"
    assert value(unit, service, "Type") == "notify"
    assert value(unit, service, "NotifyAccess") == "main"
    assert int(value(unit, service, "WatchdogSec")) > 0
    assert value(unit, service, "Restart") == "on-failure"
    assert value(unit, service, "RestartSec")
    assert value(unit, "Unit", "StartLimitIntervalSec")
    assert value(unit, "Unit", "StartLimitBurst")
    # One unprivileged user for every service: Zenoh's /dev/shm files are mode 0600.
    assert value(unit, service, "User") == "topseg"
    assert value(unit, service, "DynamicUser") in (None, "no")
    for key in ("RemoveIPC", "PrivateIPC"):  # would break shared memory between units
        assert value(unit, service, key) in (None, "no"), key
    assert value(unit, service, "NoNewPrivileges") == "yes"
    assert value(unit, service, "ProtectSystem") == "strict"
    assert value(unit, service, "ExecStart").startswith(INSTALLED_TOPSEG + " ")
    assert value(unit, "Install", "WantedBy") == "multi-user.target"


def test_driver_reaches_usb_devices():
    unit = parse_unit(UNITS / "topseg-driver@.service")
    assert value(unit, "Service", "PrivateDevices") in (None, "no")
    assert "char-usb_device rw" in values(unit, "Service", "DeviceAllow")
    groups = " ".join(values(unit, "Service", "SupplementaryGroups")).split()
    assert {"plugdev", "video"} <= set(groups)
    families = " ".join(values(unit, "Service", "RestrictAddressFamilies")).split()
    assert "AF_NETLINK" in families  # libusb hotplug


def test_worker_can_jit():
    """numba needs writable+executable memory and a writable cache directory."""
    unit = parse_unit(UNITS / "topseg-worker@.service")
    assert value(unit, "Service", "MemoryDenyWriteExecute") in (None, "no")
    env = " ".join(values(unit, "Service", "Environment"))
    assert "NUMBA_CACHE_DIR=/var/cache/topseg/" in env
    assert value(unit, "Service", "CacheDirectory") == "topseg"


def exec_argv(name: str, instance: str) -> list[str]:
    """ExecStart of a unit instance as topseg's argv, with /etc/topseg/ -> deploy/config/."""
    unit = parse_unit(UNITS / name)
    line = value(unit, "Service", "ExecStart").replace("%i", instance)
    argv = shlex.split(line)
    assert argv[0] == INSTALLED_TOPSEG
    return [a.replace("/etc/topseg/", f"{CONFIGS}/") for a in argv[1:]]


@pytest.mark.parametrize(
    "name,instance", [(n, i) for n, insts in sorted(UNIT_INSTANCES.items()) for i in insts]
)
def test_units_start_with_the_example_configs(name, instance):
    """Each unit's command line parses with its example config: every key is an option."""
    argv = exec_argv(name, instance)
    config = Path(argv[argv.index("--config") + 1])
    assert config.is_file(), f"no example config {config.name} in deploy/config/"
    args = cli.build_parser(argv).parse_args(argv)
    command = argv[0]
    if command == "driver":
        assert args.source and args.cell and args.camera == instance
    elif command == "worker":
        assert args.model == "/opt/topseg/models/default.npz"
        if instance != "worker":
            assert [c.split("/")[1] for c in args.cameras] == [instance]
    elif command == "viewer":
        assert args.web and not args.save
    elif command == "router":
        assert args.zenoh_config == "/etc/topseg/zenoh/router.json5"
    elif command == "bridge":
        assert args.target == "ros2" and args.domain == 0
    elif command == "safety":
        assert args.cell == f"/etc/topseg/{instance}.cell.toml"


def test_example_configs_are_all_used():
    used = {
        Path(a).name
        for n, insts in UNIT_INSTANCES.items()
        for i in insts
        for a in exec_argv(n, i)
        if a.endswith(".toml")
    }
    cell_files = {Path(tomllib.loads((CONFIGS / name).read_text())["safety"]["cell"]).name
                  for name in list(used) if name.startswith("safety-")}  # fmt: skip
    assert used | cell_files == {p.name for p in CONFIGS.glob("*.toml")}


UDEV_RULES = DEPLOY / "99-topseg.rules"
SENSORS = [("045e", "02ae"), ("045e", "02ad"), ("045e", "02b0"), ("03e7", "2485"), ("03e7", "f63b")]


def udev_rules() -> list[dict[str, str]]:
    """The rules as {KEY: value} (KEY with its operator, e.g. 'ATTR{idVendor}==')."""
    rules = []
    for line in UDEV_RULES.read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        rule = {}
        for m in re.finditer(
            r'\s*([A-Za-z_]+(?:\{[^}]*\})?)\s*(==|!=|\+=|-=|:=|=)\s*"([^"]*)"', line
        ):
            rule[m[1] + m[2]] = m[3]
        assert rule, f"cannot read udev rule: {line}"
        rules.append(rule)
    return rules


@pytest.mark.parametrize("vendor,product", SENSORS)
def test_udev_rule_gives_the_sensor_to_a_group(vendor, product):
    matching = [
        r
        for r in udev_rules()
        if r.get("ATTR{idVendor}==") == vendor and r.get("ATTR{idProduct}==") in (product, None)
    ]
    assert matching, f"no udev rule for {vendor}:{product}"
    for rule in matching:
        assert rule.get("SUBSYSTEM==") == "usb"
        assert rule.get("GROUP=") == "plugdev"
        mode = int(rule.get("MODE=", "0"), 8)
        assert mode == 0o660, oct(mode)


def test_udev_rules_never_world_writable():
    for rule in udev_rules():
        mode = rule.get("MODE=")
        if mode is not None:
            assert not int(mode, 8) & 0o002, rule


# --- deploy/install.sh and deploy/uninstall.sh into a temporary root ----------------------


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """A topseg wheel built from the package sources, so that installing needs no network."""
    src = tmp_path_factory.mktemp("src")
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    for name in ("topseg_pkg", "core", "drivers", "services"):
        shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__"))
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
         "-w", str(out), str(src)],
        check=True,
        timeout=300,
    )  # fmt: skip
    (found,) = out.glob("topseg-*.whl")
    return found


@pytest.fixture
def checkout(tmp_path) -> Path:
    """A checkout whose deploy/ the test may change (the scripts are the real ones)."""
    co = tmp_path / "checkout"
    shutil.copytree(DEPLOY, co / "deploy")
    for name in ("models", "recordings", "docs"):
        (co / name).symlink_to(ROOT / name)
    return co


def run_script(script: Path, *args: str) -> list[str]:
    result = subprocess.run(
        ["bash", str(script), *args], capture_output=True, text=True, timeout=300
    )
    assert result.returncode == 0, result.stdout + result.stderr
    return result.stdout.splitlines()


def install(checkout: Path, root: Path, wheel: Path) -> list[str]:
    return run_script(
        checkout / "deploy" / "install.sh",
        "--root", str(root), "--no-systemctl", "--python", sys.executable, "--no-venv-pip",
        "--source", str(wheel), "--pip-args", "--no-deps --no-index",
    )  # fmt: skip


def snapshot(root: Path) -> dict[str, tuple]:
    """Every file and link under root: content digest, mode and mtime (to see any change)."""
    found = {}
    for path in sorted(root.rglob("*")):
        st = path.lstat()
        digest = None
        if path.is_file() and not path.is_symlink():
            digest = hashlib.sha256(path.read_bytes()).hexdigest()
        found[str(path.relative_to(root))] = (digest, st.st_mode, st.st_mtime_ns)
    return found


def lines_with(lines: list[str], text: str) -> list[str]:
    return [line for line in lines if text in line]


def test_every_units_documentation_is_installed(tmp_path, checkout, wheel):
    """Each unit's `Documentation=file:/opt/...` names a page install.sh puts there."""
    root = tmp_path / "root"
    install(checkout, root, wheel)
    pages = []
    for unit in sorted((DEPLOY / "systemd").glob("*.service")):
        pages += re.findall(r"^Documentation=file:/(\S+)$", unit.read_text(), re.M)
    assert pages, "no Documentation= lines"
    missing = [page for page in pages if not (root / page).is_file()]
    assert not missing, f"units name documentation install.sh does not install: {missing}"


@pytest.mark.parametrize("extras, installed", [("oak", "cell,oak"), ("", "cell")])
def test_install_always_takes_the_cell_extra(tmp_path, checkout, wheel, extras, installed):
    """The live services' packages come with every install; --extras adds sensors' SDKs."""
    lines = run_script(
        checkout / "deploy" / "install.sh",
        "--root", str(tmp_path / "root"), "--no-systemctl", "--python", sys.executable,
        "--no-venv-pip", "--no-compile", "--source", str(wheel),
        "--pip-args", "--no-deps --no-index", "--extras", extras,
    )  # fmt: skip
    assert lines_with(lines, f", extras {installed})"), lines


def test_install_twice_then_uninstall(tmp_path, checkout, wheel):
    root = tmp_path / "root"
    first = install(checkout, root, wheel)
    assert lines_with(first, "installed topseg into /opt/topseg/venv (topseg ")
    for path in (
        "etc/systemd/system/topseg-driver@.service",
        "etc/systemd/system/topseg-worker@.service",
        "etc/systemd/system/topseg-viewer.service",
        "etc/systemd/system/topseg-router.service",
        "etc/udev/rules.d/99-topseg.rules",
        "etc/topseg/kinect.toml",
        "etc/topseg/oak.toml",
        "opt/topseg/models/default.npz",
        "opt/topseg/recordings/demo.mcap",
    ):
        assert (root / path).is_file(), path
        assert lines_with(first, f"installed /{path}"), path
    for conf in (DEPLOY / "zenoh").glob("*.json5"):
        assert (root / "etc/topseg/zenoh" / conf.name).is_file()
    assert (root / "etc/topseg/kinect.toml").stat().st_mode & 0o777 == 0o640
    assert (root / "etc/topseg").stat().st_mode & 0o777 == 0o750
    topseg = root / "opt/topseg/venv/bin/topseg"
    version = subprocess.run([topseg, "--version"], capture_output=True, text=True, timeout=60)
    assert version.stdout.startswith("topseg ")

    before = snapshot(root)
    second = install(checkout, root, wheel)
    assert snapshot(root) == before, "a second install changed files"
    changed = [line for line in second if "installed" in line or "updated" in line]
    assert not changed, changed
    assert lines_with(second, "unchanged /opt/topseg/venv")

    run_script(checkout / "deploy" / "uninstall.sh", "--root", str(root), "--no-systemctl")
    assert not (root / "opt/topseg").exists()
    assert not list((root / "etc/systemd/system").glob("topseg-*"))
    assert not (root / "etc/udev/rules.d/99-topseg.rules").exists()
    assert (root / "etc/topseg/kinect.toml").is_file(), "configs are kept without --purge"
    before = snapshot(root)
    again = run_script(checkout / "deploy" / "uninstall.sh", "--root", str(root), "--no-systemctl")
    assert snapshot(root) == before
    assert not lines_with(again, "removed")
    run_script(
        checkout / "deploy" / "uninstall.sh", "--root", str(root), "--no-systemctl", "--purge"
    )
    assert not (root / "etc/topseg").exists()


@pytest.mark.slow
def test_install_keeps_edited_configs(tmp_path, checkout, wheel):
    root = tmp_path / "root"
    install(checkout, root, wheel)
    etc = root / "etc/topseg"
    (etc / "viewer.toml").write_text("[viewer]\nweb = true\nstride = 2\n")  # edited
    (etc / "oak.toml").write_text('[driver]\nsource = "oak"\ncamera = "left"\n')  # edited
    # A new release changes the defaults of kinect.toml (unedited) and oak.toml (edited).
    for name in ("kinect.toml", "oak.toml"):
        with open(checkout / "deploy/config" / name, "a") as f:
            f.write("# a newer default\n")
    lines = install(checkout, root, wheel)
    assert lines_with(lines, "updated /etc/topseg/kinect.toml")
    assert (etc / "kinect.toml").read_text().endswith("# a newer default\n")
    assert lines_with(lines, "kept your edited /etc/topseg/viewer.toml")
    assert not (etc / "viewer.toml.dist").exists()
    assert (etc / "viewer.toml").read_text().endswith("stride = 2\n")
    assert lines_with(lines, "kept your edited /etc/topseg/oak.toml; the new default is")
    assert 'camera = "left"' in (etc / "oak.toml").read_text()
    assert (etc / "oak.toml.dist").read_text() == (checkout / "deploy/config/oak.toml").read_text()
    before = snapshot(root)
    install(checkout, root, wheel)
    assert snapshot(root) == before


@needs_analyze
def test_installed_units_verify_in_the_root(tmp_path, checkout, wheel):
    """`systemd-analyze verify --root`: the installed units start the installed topseg."""
    root = tmp_path / "root"
    install(checkout, root, wheel)
    shutil.copytree("/usr/lib/systemd/system", root / "usr/lib/systemd/system", symlinks=True)
    units = ["topseg-driver@kinect.service", "topseg-worker@kinect.service"]
    units += ["topseg-viewer.service", "topseg-router.service", "topseg-bridge-ros2.service"]
    result = subprocess.run(
        [SYSTEMD_ANALYZE, "verify", f"--root={root}", *units],
        capture_output=True,
        text=True,
        timeout=60,
    )
    output = (result.stdout + result.stderr).strip()
    assert result.returncode == 0 and output == "", output


# --- the hardening keeps Zenoh's shared memory ---------------------------------------------

#: The mount layout systemd gives the worker, viewer and router (PrivateDevices=: a private
#: /dev with the host's /dev/shm bind-mounted in; PrivateTmp=; ProtectSystem=strict: / read
#: only), made with unshare(1); $1 = host keeps /dev/shm as systemd does, private replaces it.
#: $3 is a directory under /tmp to keep visible (a checkout under /tmp, as a CI clone may be:
#: the installed units run from /opt), or "".
SANDBOX = r"""
set -e
dev=$2
keep=$3
mount -t tmpfs -o mode=755 tmpfs "$dev"
for d in null zero random urandom; do touch "$dev/$d"; mount --bind "/dev/$d" "$dev/$d"; done
mkdir "$dev/shm"
if [ "$1" = host ]; then mount --bind /dev/shm "$dev/shm"; else mount -t tmpfs tmpfs "$dev/shm"; fi
mount --move "$dev" /dev
if [ -n "$keep" ]; then mkdir /dev/.keep; mount --rbind "$keep" /dev/.keep; fi
mount -t tmpfs tmpfs /tmp
if [ -n "$keep" ]; then mkdir -p "$keep"; mount --move /dev/.keep "$keep"; rmdir /dev/.keep; fi
mount -o remount,bind,ro /
shift 3
exec "$@"
"""

#: Receives depth messages, then says whether its transport to the driver uses shared memory.
COUNT = r"""
import json, sys, threading, time
import zenoh
from topseg.services.runtime import zenoh_session
sizes = []
enough = threading.Event()
def on(sample):
    sizes.append(len(sample.payload.to_bytes()))
    if len(sizes) >= 5:
        enough.set()
session = zenoh_session.open_session(None, int(sys.argv[1]))
sub = session.declare_subscriber("topseg/*/*/depth", on)
enough.wait(30)
print(json.dumps({"n": len(sizes), "size": max(sizes, default=0),
                  "shm": [t.is_shm for t in session.info.transports()]}))
session.close()
"""


def can_unshare() -> bool:
    if shutil.which("unshare") is None:
        return False
    probe = ["unshare", "-m", "--propagation", "private", "mount", "-t", "tmpfs", "t", "/mnt"]
    return subprocess.run(probe, capture_output=True, timeout=30).returncode == 0


@pytest.mark.skipif(
    not sys.platform.startswith("linux") or not can_unshare(),
    reason="needs root and mount namespaces (unshare -m) to build the units' sandbox",
)
@pytest.mark.slow
@pytest.mark.parametrize("shm", ["host", "private"])
def test_sandboxed_worker_gets_frames_by_shared_memory(shm, tmp_path):
    """Under the units' mount layout a subscriber still shares memory with the driver.

    The control (a private /dev/shm, as a unit with its own /dev/shm tmpfs would have)
    shows the check can fail: Zenoh then falls back to TCP.
    """
    port = free_port()
    services = Services()
    try:
        driver = services(
            "driver", "--source", f"replay:{ROOT}/recordings/demo.mcap", "--loop",
            "--zenoh-port", port,
        )  # fmt: skip
        driver.wait_line("publishing")
        dev = tmp_path / "dev"
        dev.mkdir()
        keep = str(ROOT) if ROOT.is_relative_to("/tmp") else ""
        result = subprocess.run(
            ["unshare", "-m", "--propagation", "private", "bash", "-c", SANDBOX, "sandbox",
             shm, str(dev), keep, sys.executable, "-c", COUNT, str(port)],
            capture_output=True, text=True, timeout=90, cwd="/",
        )  # fmt: skip
        assert result.returncode == 0, result.stderr
        seen = json.loads(result.stdout.strip().splitlines()[-1])
    finally:
        services.close()
    assert seen["n"] >= 5 and seen["size"] > 600_000, seen  # 640x480 frames arrive either way
    assert seen["shm"] == [shm == "host"], seen


#: Runs install.sh and uninstall.sh for "/" inside a mount namespace where /etc is a copy and
#: /opt, /var/lib, /var/cache and /var/log are empty tmpfs: the real system is never touched.
#: $1 = the copy of /etc, $2 = the wheel, $3 = the Python, $4 = the checkout.
AS_ROOT = r"""
set -euo pipefail
mount --bind "$1" /etc
for d in /opt /var/lib /var/cache /var/log; do mount -t tmpfs tmpfs "$d"; done
for d in /etc /opt /var/lib /var/cache /var/log; do mountpoint -q "$d"; done
args=(--python "$3" --no-venv-pip --source "$2" --pip-args "--no-deps --no-index")
echo "== first"; bash "$4/deploy/install.sh" "${args[@]}"
echo "== second"; bash "$4/deploy/install.sh" "${args[@]}"
echo "== user"; id topseg
echo "== etc"; stat -c '%U:%G %a %n' /etc/topseg /etc/topseg/kinect.toml
echo "== cache"; stat -c '%U:%G %a %n' /var/cache/topseg/numba
echo "== uninstall"; bash "$4/deploy/uninstall.sh" --purge
echo "== after"; getent passwd topseg || echo "no user topseg"
"""


@pytest.mark.skipif(
    not sys.platform.startswith("linux") or not can_unshare(),
    reason="needs root and mount namespaces (unshare -m) to install for / in isolation",
)
@pytest.mark.slow
def test_install_for_root_creates_the_user(tmp_path, checkout, wheel):
    """The parts only a real install runs: the user in plugdev and video, /etc/topseg
    readable by its group, and uninstall --purge removing the user again."""
    etc = tmp_path / "etc"
    shutil.copytree("/etc", etc, symlinks=True, ignore_dangling_symlinks=True)
    result = subprocess.run(
        ["unshare", "-m", "--propagation", "private", "bash", "-c", AS_ROOT, "as-root",
         str(etc), str(wheel), sys.executable, str(checkout)],
        capture_output=True, text=True, timeout=300, cwd="/",
    )  # fmt: skip
    out = result.stdout
    assert result.returncode == 0, out + result.stderr
    sections = {}  # {name: its lines}
    for part in out.split("== ")[1:]:
        name, _, text = part.partition("\n")
        sections[name] = text
    assert "install: created user topseg (groups plugdev, video)" in sections["first"]
    # the kernels are compiled as the topseg user into the services' cache; this venv was
    # installed --no-deps (no numba) from a Python the topseg user may not run, so that
    # fails, and the install says why and goes on
    assert (
        "install: warning: could not compile numba's kernels into /var/cache/topseg/numba "
        "(the worker will on its first start): " in sections["first"]
    ), sections["first"]
    changed = [
        line
        for line in sections["second"].splitlines()
        if any(word in line for word in ("created", "installed", "updated", "added"))
    ]
    assert not changed, changed
    assert "unchanged user topseg" in sections["second"]
    groups = sections["user"]
    assert "(plugdev)" in groups and "(video)" in groups, groups
    assert sections["etc"].split("\n")[:2] == [
        "root:topseg 750 /etc/topseg",
        "root:topseg 640 /etc/topseg/kinect.toml",
    ]
    assert sections["cache"].split("\n")[0] == "topseg:topseg 750 /var/cache/topseg/numba"
    assert "removed user topseg" in sections["uninstall"]
    assert "no user topseg" in sections["after"]
