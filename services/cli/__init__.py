"""The `topseg` command: one entry point, one module per subcommand.

Each subcommand module exposes `add_arguments(parser)` and `run(args) -> int`, and keeps
heavy imports inside `run` so that `topseg --help` stays fast.
"""

from __future__ import annotations

import argparse
import atexit
import importlib
import logging
import os
import re
import sys
import warnings

from topseg import __version__
from topseg.core.errors import TopsegError
from topseg.services.cli import config_file, describe
from topseg.services.runtime import systemd_notify

#: subcommand -> (module, one-line help). Add a line here to add a command.
COMMANDS: dict[str, tuple[str, str]] = {
    "demo": (
        "topseg.services.batch.demo",
        "run the main job end to end and print what it measured",
    ),
    "train": (
        "topseg.services.batch.train",
        "train a forest on a dataset (Dask), write a model file",
    ),
    "evaluate": (
        "topseg.services.batch.evaluate",
        "score a model on a dataset: per-class table, JSON, plots",
    ),
    "person-check": (
        "topseg.services.batch.person_check",
        "fit a model's person check on a dataset, write it into the model file",
    ),
    "segment": (
        "topseg.services.batch.segment",
        "segment depth PNGs or recordings offline into label PNGs",
    ),
    "experiment": (
        "topseg.services.batch.experiment",
        "the paper's experiments (Fig. 4, Table I); one model across mounts and sensors",
    ),
    "bench": ("topseg.services.batch.bench", "measure speed and memory of a stage"),
    "driver": ("topseg.services.live.driver", "publish one camera's depth frames on Zenoh"),
    "record": ("topseg.services.live.record", "record Zenoh topseg messages to an MCAP file"),
    "devices": ("topseg.services.live.devices", "list attached depth sensors and how to use them"),
    "datagen": (
        "topseg.services.batch.datagen",
        "render a synthetic dataset (Zarr) on Dask; preview it",
    ),
    "worker": ("topseg.services.live.worker", "label depth on Zenoh: forest + CRF, labels, stats"),
    "viewer": ("topseg.services.live.viewer", "show depth, labels, points and stats in Rerun"),
    "router": (
        "topseg.services.live.router",
        "run a Zenoh router (for several machines, see deploy/)",
    ),
    "bridge": (
        "topseg.services.live.bridge_ros2",
        "publish depth, labels, camera info and mounts to ROS 2 (rmw_zenoh)",
    ),
    "safety": (
        "topseg.services.live.safety",
        "a cell's state from labels and the robot's joints: clear, warning or stop",
    ),
    "status": (
        "topseg.services.live.status",
        "each camera's driver and worker: alive, fps, latency",
    ),
    "calibrate": (
        "topseg.services.live.calibrate",
        "fit the floor in a camera's frames, write a mount file",
    ),
    "compile": (
        "topseg.services.cli.compile_kernels",
        "compile numba's kernels into its cache, so that services start in seconds",
    ),
}


#: The commands that run as live services over Zenoh: once one has stopped cleanly, its
#: process ends without the interpreter's teardown (`console`).
LIVE_SERVICES = frozenset({"driver", "record", "worker", "viewer", "router", "bridge", "safety"})

#: subcommand -> the page its `--help` sends a user to for the details ("Details: ...")
DETAILS: dict[str, str] = {
    "demo": "docs/tutorial.md",
    "train": "docs/howto/retrain.md",
    "evaluate": "docs/howto/retrain.md",
    "person-check": "docs/howto/retrain.md",
    "segment": "docs/howto/label-offline.md",
    "experiment": "docs/results.md",
    "bench": "docs/performance.md",
    "driver": "docs/reference/services.md#driver",
    "record": "docs/reference/services.md#record",
    "devices": "docs/howto/add-sensor.md",
    "datagen": "docs/howto/retrain.md",
    "worker": "docs/reference/services.md#worker",
    "viewer": "docs/reference/services.md#viewer",
    "router": "docs/reference/services.md#router",
    "bridge": "docs/howto/ros2.md",
    "safety": "docs/howto/safety.md",
    "status": "docs/reference/services.md#status",
    "calibrate": "docs/howto/calibrate.md",
    "compile": "docs/howto/deploy.md",
}


class UsageError(TopsegError):
    """A command line argparse refuses (a bad option value, a missing argument)."""


class OneLineParser(argparse.ArgumentParser):
    """A subcommand's parser: a bad command line is one error line naming the option and exit
    2 (`main`), not usage text; `--help` still prints the usage."""

    def error(self, message: str):  # type: ignore[override]
        """Raise UsageError(message) instead of printing usage and exiting; a value refused
        by a `options` check reads `--fps must be in [0.1, 1000], got 1e-300`."""
        m = re.fullmatch(r"argument ([^:/\s]+)(?:/\S+)?: (must .*)", message, re.S)
        raise UsageError(f"{m[1]} {m[2]}" if m else message)


LOG_FORMAT = "%(asctime)s %(levelname)-7s %(name)s: %(message)s"


def setup_logging(verbose: int = 0) -> None:
    """One log format for every service, on stderr."""
    level = logging.DEBUG if verbose > 1 else logging.INFO if verbose == 1 else logging.WARNING
    # Libraries (dask, numba, zenoh) log warnings only; topseg's own loggers at `level`.
    logging.basicConfig(level=logging.WARNING, format=LOG_FORMAT, stream=sys.stderr, force=True)
    logging.getLogger("topseg").setLevel(level)


def named_command(argv: list[str]) -> str | None:
    """The first word of `argv` that is a subcommand, or None."""
    return next((a for a in argv if a in COMMANDS), None)


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser; only the module of the command named in `argv` is imported.

    So `topseg --help` stays instant and one command's import error never breaks another.
    """
    argv = sys.argv[1:] if argv is None else argv
    chosen = named_command(argv)
    parser = argparse.ArgumentParser(
        prog="topseg",
        description="Real-time segmentation of top-view depth frames (see docs/index.md).",
    )
    parser.add_argument("--version", action="version", version=f"topseg {__version__}")
    parser.add_argument(
        "-v", "--verbose", action="count", default=1, help="more log output (-vv for debug)"
    )
    parser.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=OneLineParser)
    sub.required = True
    for name, (module_name, help_text) in COMMANDS.items():
        if name != chosen:
            sub.add_parser(name, help=help_text)
            continue
        module = importlib.import_module(module_name)
        p = sub.add_parser(
            name,
            help=help_text,
            description=describe.description(module.__doc__, DETAILS.get(name)),
            formatter_class=describe.ParagraphFormatter,
        )
        module.add_arguments(p)
        config_file.add_arguments(p, name, argv, COMMANDS)  # --config FILE: TOML defaults
        p.set_defaults(_run=module.run)
    return parser


def fail(command: str | None, exc: BaseException) -> None:
    """The one error line, on stderr and (under systemd) as the unit's STATUS=."""
    line = f"topseg {command}: error: {exc}" if command else f"topseg: error: {exc}"
    print(line, file=sys.stderr)
    cause = exc if isinstance(exc, OSError) else exc.__cause__ or exc.__context__
    systemd_notify.failed(line, getattr(cause, "errno", None))


#: OpenMP threads (numba's parallel kernels) sleep between parallel regions instead of
#: spinning: on the 2-core target a driver, a viewer and the worker share the cores, and
#: spinning threads took their time (docs/explanation/speed.md). The environment can override it.
OMP_WAIT_POLICY = "PASSIVE"


def main(argv: list[str] | None = None) -> int:
    """Run one `topseg` command; its exit code (2 with one error line on a TopsegError)."""
    os.environ.setdefault("OMP_WAIT_POLICY", OMP_WAIT_POLICY)  # before any kernel runs
    try:
        args = build_parser(argv).parse_args(argv)
    except TopsegError as exc:  # a bad --config file
        fail(named_command(argv or sys.argv[1:]), exc)
        return 2
    setup_logging(0 if args.quiet else args.verbose)
    try:
        return int(args._run(args) or 0)
    except KeyboardInterrupt:
        # an interrupt can leave zarr's async reads half done; their "coroutine was never
        # awaited" warnings at exit would bury this line, which is the whole story
        warnings.simplefilter("ignore")
        # ... and asyncio logs the pending tasks it destroys at exit ("Task was destroyed but
        # it is pending!") through its logger, not as warnings
        logging.getLogger("asyncio").setLevel(logging.CRITICAL + 1)
        print("topseg: interrupted", file=sys.stderr)
        return 130
    except TopsegError as exc:
        fail(args.command, exc)
        return 2
    except Exception as exc:
        systemd_notify.failed(f"topseg {args.command}: crashed: {type(exc).__name__}: {exc}")
        raise


def console() -> None:
    """The `topseg` executable: `main`, and then a live service's process ends at once, its
    exit handlers run and its output flushed. The interpreter's teardown would stop the
    threads that Zenoh's, Foxglove's and Rerun's Rust runtimes still run, and a thread stopped
    inside Rust aborts the process ("FATAL: exception not rethrown", SIGABRT) after the
    service had stopped cleanly: a crash in systemd's log for a clean stop."""
    argv = sys.argv[1:]
    code = main(argv)
    if named_command(argv) not in LIVE_SERVICES:
        sys.exit(code)
    atexit._run_exitfuncs()  # what a normal exit runs first: logging's flush, Rerun's
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
