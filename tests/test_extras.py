"""A cell install (`topseg[cell]`) runs the live services without the synthesis and training
stack or a sensor's SDK: proved in Python processes where those packages cannot be imported,
and by checking that pyproject.toml's extras hold every package the live code imports."""

import ast
import json
import os
import re
import subprocess
import sys
import tomllib
from importlib import metadata
from pathlib import Path

import pytest
from test_import_graph import _type_checking_only, import_graph, module_files

REPO = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())

#: what a cell install leaves out: the training stack and the sensor SDKs
NOT_ON_A_CELL = (
    "pybullet", "pybullet_data", "dask", "distributed", "zarr", "matplotlib",
    "yourdfpy", "trimesh", "fast_simplification", "xacrodoc", "xacro", "rtbdata",
    "depthai", "openni", "freenect",
)  # fmt: skip

#: the live code's imports of packages a cell may lack, each behind a one-line message that
#: names the extra which installs it: import name -> extra
OPTIONAL_IN_LIVE = {
    "pybullet": "train",  # --source synthetic, `topseg compile synthesis`
    "pybullet_data": "train",
    "matplotlib": "train",  # the picture of `topseg calibrate`
    "depthai": "oak",
    "openni": "openni2",
    "freenect": "kinect",
}

#: the live services' packages: what a cell PC runs
LIVE_PACKAGES = (
    "topseg.services.live",
    "topseg.services.runtime",
    "topseg.services.cli",
    "topseg.drivers",
)
CELL_COMMANDS = (
    "driver", "worker", "viewer", "bridge", "record", "status", "router", "devices",
    "calibrate", "compile",
)  # fmt: skip

#: installed as sitecustomize: every Python started with it on PYTHONPATH (a driver's reader
#: child too) finds none of the blocked packages, as on a cell install
BLOCKER = """
import sys

BLOCKED = {blocked!r}


class NotOnACell:
    def find_spec(self, name, path=None, target=None):
        if name.partition(".")[0] in BLOCKED:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
        return None


sys.meta_path.insert(0, NotOnACell())
"""

#: imports every live module and builds each cell command's parser; JSON on the last line
IMPORT_ALL = """
import contextlib, importlib, io, json, sys
from topseg.services.cli import main
from topseg.services.cli.compile_kernels import installed_jobs

modules, blocked = json.loads(sys.argv[1]), json.loads(sys.argv[2])
failed = {}
for name in modules:
    try:
        importlib.import_module(name)
    except Exception as exc:
        failed[name] = f"{type(exc).__name__}: {exc}"
helps = {}
for command in json.loads(sys.argv[3]):
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        try:
            code = main([command, "--help"])
        except SystemExit as exc:
            code = exc.code
    helps[command] = [code, out.getvalue()[-300:]]
skipped = []
jobs = installed_jobs(["forest", "synthesis"], asked=False, report=skipped.append)
loaded = sorted(m for m in sys.modules if m.partition(".")[0] in blocked)
print(json.dumps({"failed": failed, "helps": helps, "loaded": loaded, "jobs": jobs,
                  "skipped": skipped}))
"""


@pytest.fixture(scope="module")
def cell_env(tmp_path_factory) -> dict:
    """The environment of a Python that cannot import what a cell install leaves out."""
    folder = tmp_path_factory.mktemp("cell")
    (folder / "sitecustomize.py").write_text(BLOCKER.format(blocked=set(NOT_ON_A_CELL)))
    path = os.pathsep.join(p for p in (str(folder), os.environ.get("PYTHONPATH")) if p)
    return {**os.environ, "PYTHONPATH": path}


def cell_run(env: dict, *args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    """`python ARGS` in the cell environment, from a folder outside the checkout."""
    return subprocess.run(
        [sys.executable, *args], env=env, cwd="/", capture_output=True, text=True,
        timeout=timeout,
    )  # fmt: skip


def live_modules() -> list[str]:
    """Every topseg module of the live services, the runtime, the CLI and the drivers (but
    `__main__`, which runs the command when imported)."""
    names = module_files()
    return sorted(n for n in names if n.startswith(LIVE_PACKAGES) and not n.endswith("__main__"))


def test_the_blocker_blocks(cell_env):
    result = cell_run(cell_env, "-c", "import zarr")
    assert result.returncode == 1
    assert "ModuleNotFoundError: No module named 'zarr'" in result.stderr


def test_live_modules_import_and_cell_commands_parse_without_the_training_stack(cell_env):
    modules = live_modules()
    assert "topseg.services.live.worker" in modules and "topseg.drivers.oak" in modules
    result = cell_run(
        cell_env, "-c", IMPORT_ALL, json.dumps(modules), json.dumps(NOT_ON_A_CELL),
        json.dumps(CELL_COMMANDS),
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout.strip().splitlines()[-1])
    assert report["failed"] == {}
    assert report["loaded"] == []
    for command, (code, text) in report["helps"].items():
        assert code == 0, f"topseg {command} --help: {text}"
    assert report["jobs"] == ["forest"]
    assert report["skipped"] == [
        "skipped synthesis kernels: pybullet is not installed (pip install 'topseg[train]')"
    ]


@pytest.mark.parametrize(
    "source, line",
    [
        ("oak", "oak: depthai is not installed (pip install 'topseg[oak]')"),
        ("openni2", "openni2: openni is not installed (pip install 'topseg[openni2]')"),
        ("freenect", "freenect: freenect is not installed (pip install 'topseg[kinect]')"),
        ("synthetic", "synthetic: pybullet is not installed (pip install 'topseg[train]')"),
    ],
)
def test_a_source_without_its_package_is_one_line_naming_the_extra(cell_env, source, line):
    """openni2 and freenect fail in their reader child, which the blocker reaches too."""
    result = cell_run(
        cell_env, "-m", "topseg.services.cli", "driver", "--source", source, "--camera", "x"
    )
    assert result.returncode == 2, result.stderr
    (only,) = result.stderr.strip().splitlines()
    assert only.startswith(f"topseg driver: error: {line}"), only


def test_devices_names_the_oak_extra(cell_env):
    result = cell_run(cell_env, "-m", "topseg.services.cli", "devices", "--json")
    assert result.returncode == 0, result.stderr
    notes = json.loads(result.stdout)["notes"]
    assert "oak: depthai is not installed (pip install 'topseg[oak]')" in notes


@pytest.mark.slow
def test_calibrate_without_matplotlib_writes_the_mount_but_no_picture(cell_env, tmp_path):
    demo = f"replay:{REPO / 'recordings' / 'demo.mcap'}"
    out = tmp_path / "mount.json"
    calibrate = ("-m", "topseg.services.cli", "calibrate", "--source", demo, "--out", str(out))
    asked = cell_run(cell_env, *calibrate, "--picture", str(tmp_path / "p.png"))
    assert asked.returncode == 2
    assert asked.stderr.strip() == (
        "topseg calibrate: error: --picture: matplotlib is not installed "
        "(pip install 'topseg[train]')"
    )
    result = cell_run(cell_env, *calibrate, "--frames", "3", timeout=300)
    assert result.returncode == 0, result.stderr
    assert out.is_file() and list(tmp_path.glob("*.png")) == []
    assert (
        "picture    not written: matplotlib is not installed (pip install 'topseg[train]')"
    ) in result.stdout.splitlines()


# --- pyproject.toml's extras against the imports ------------------------------------------


def requirement_name(text: str) -> str:
    """`dask[distributed]>=2024.1` -> `dask`, normalised as pip compares names."""
    name = re.match(r"[A-Za-z0-9._-]+", text.strip())[0]
    return re.sub(r"[-_.]+", "-", name).lower()


def extra(name: str) -> set[str]:
    """The distributions an extra names, its `topseg[...]` references followed."""
    out = set()
    for text in PYPROJECT["project"]["optional-dependencies"][name]:
        if m := re.fullmatch(r"topseg\[([\w,-]+)\]", text.replace(" ", "")):
            for inner in m[1].split(","):
                out |= extra(inner)
        else:
            out.add(requirement_name(text))
    return out


def with_requirements(names: set[str]) -> set[str]:
    """`names` and everything they require (no extras of theirs), as installed here."""
    out, todo = set(), list(names)
    while todo:
        name = todo.pop()
        if name in out:
            continue
        out.add(name)
        try:
            requires = metadata.requires(name) or []
        except metadata.PackageNotFoundError:
            continue
        todo += [requirement_name(r) for r in requires if "extra ==" not in r]
    return out


def third_party_imports(path: Path) -> set[tuple[str, bool]]:
    """(top-level name, made inside a function) of each non-stdlib, non-topseg import."""
    found = set()

    def visit(node: ast.AST, in_function: bool) -> None:
        if isinstance(node, ast.If) and _type_checking_only(node):
            for child in node.orelse:
                visit(child, in_function)
            return
        names = []
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            names = [node.module]
        for name in names:
            top = name.partition(".")[0]
            if top not in sys.stdlib_module_names and top not in ("topseg", "__future__"):
                found.add((top, in_function))
        inner = in_function or isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
        for child in ast.iter_child_nodes(node):
            visit(child, inner)

    visit(ast.parse(path.read_text(), str(path)), False)
    return found


def reached(include_functions: bool) -> dict[str, set[str]]:
    """Third-party import name -> the topseg modules importing it, over every module the
    live modules reach (a package's parents included)."""
    graph, files = import_graph(include_functions, type_checking=False), module_files()
    seen, todo = set(), live_modules()
    while todo:
        name = todo.pop()
        if name in seen or name not in files:
            continue
        seen.add(name)
        todo += [*graph[name], *(name.rsplit(".", k)[0] for k in range(1, name.count(".")))]
    out: dict[str, set[str]] = {}
    for name in seen:
        for top, in_function in third_party_imports(files[name]):
            if include_functions or not in_function:
                out.setdefault(top, set()).add(name)
    return out


def distribution_of(module: str) -> str:
    """The installed distribution that provides import name `module`."""
    (name, *_) = metadata.packages_distributions()[module]
    return requirement_name(name)


def cell_provides() -> set[str]:
    """What `pip install topseg[cell]` installs (as this environment resolves it)."""
    core = {requirement_name(r) for r in PYPROJECT["project"]["dependencies"]}
    return with_requirements(core | extra("cell"))


@pytest.mark.slow
def test_the_walker_finds_imports():
    found = reached(include_functions=True)
    assert "topseg.services.live.viewer" in found["rerun"]
    assert "topseg.drivers.oak" in found["depthai"]
    assert "topseg.core.formats.wire" in reached(include_functions=False)["msgpack"]


@pytest.mark.slow
def test_every_package_a_live_module_imports_comes_with_the_cell_extra():
    provides = cell_provides()
    missing = {
        module: sorted(where)[:3]
        for module, where in reached(include_functions=True).items()
        if module not in OPTIONAL_IN_LIVE and distribution_of(module) not in provides
    }
    assert not missing, f"live code imports these, which topseg[cell] lacks: {missing}"


def test_no_live_module_imports_an_optional_package_at_module_top():
    at_top = reached(include_functions=False)
    bad = {m: sorted(at_top[m]) for m in OPTIONAL_IN_LIVE if m in at_top}
    assert not bad, bad
    provides = cell_provides()
    assert all(distribution_of(m) in provides for m in at_top), at_top


@pytest.mark.parametrize("module, name", sorted(OPTIONAL_IN_LIVE.items()))
def test_each_optional_package_is_in_the_extra_its_message_names(module, name):
    distribution = {"pybullet_data": "pybullet"}.get(module, module)
    assert requirement_name(distribution) in extra(name)
    assert requirement_name(distribution) not in cell_provides()


def test_all_holds_every_extra_but_kinect_and_test():
    extras = PYPROJECT["project"]["optional-dependencies"]
    everything = set().union(*(extra(n) for n in extras if n not in ("all", "kinect", "test")))
    assert extra("all") == everything


@pytest.mark.parametrize(
    "package", ["pybullet", "dask", "zarr", "matplotlib", "depthai", "openni", "freenect"]
)
def test_the_core_and_cell_leave_out_the_training_stack_and_sdks(package):
    core = {requirement_name(r) for r in PYPROJECT["project"]["dependencies"]}
    assert package not in core | extra("cell")


def test_every_package_is_installed():
    """A package left out of pyproject's list works from the checkout but not installed."""
    packages = {n for n, path in module_files().items() if path.name == "__init__.py"}
    assert packages <= set(PYPROJECT["tool"]["setuptools"]["packages"])


def test_the_installers_ask_for_the_extras():
    make = (REPO / "scripts" / "install.sh").read_text()
    assert '-e ".[all,kinect,test]"' in make
    cell = (REPO / "deploy" / "install.sh").read_text()
    assert "EXTRAS=cell${EXTRAS:+,$EXTRAS}" in cell
