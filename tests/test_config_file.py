"""`topseg <command> --config FILE`: TOML defaults that the command line overrides, a shared
[zenoh] table, $TOPSEG_CONFIG, and one clear error (with file:line) for anything wrong.
(Whole processes refusing bad configs are in test_reliability_config.py.)"""

from __future__ import annotations

import pytest

from topseg.core.errors import TopsegError
from topseg.services import cli
from topseg.services.cli import config_file


def parse(*argv):
    argv = [str(a) for a in argv]
    return cli.build_parser(argv).parse_args(argv)


def write(tmp_path, text, name="cam.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_file_gives_defaults_and_the_command_line_wins(tmp_path):
    path = write(
        tmp_path,
        '[zenoh]\nzenoh-port = 7500\n\n[driver]\nsource = "synthetic"\ncamera = "top"\n'
        "fps = 12\nloop = true\nzenoh_port = 7600\n",
    )
    args = parse("driver", "--config", path)
    assert (args.source, args.camera, args.fps, args.loop) == ("synthetic", "top", 12.0, True)
    assert args.zenoh_port == 7600  # the command's table wins over [zenoh]
    args = parse("driver", "--config", path, "--camera", "side", "--zenoh-port", "7700")
    assert (args.camera, args.zenoh_port, args.source) == ("side", 7700, "synthetic")


def test_required_option_may_come_from_the_file(tmp_path):
    path = write(tmp_path, '[worker]\nmodel = "/m.npz"\ncameras = ["c/a", "c/b"]\n')
    args = parse("worker", "--config", path)
    assert args.model == "/m.npz" and args.cameras == ["c/a", "c/b"]


def test_one_file_serves_driver_and_worker(tmp_path):
    path = write(
        tmp_path,
        '[zenoh]\nzenoh-config = "/etc/z.json5"\n[driver]\nsource = "synthetic"\n'
        '[worker]\nmodel = "/m.npz"\n',
    )
    assert parse("driver", "--config", path).zenoh_config == "/etc/z.json5"
    worker = parse("worker", "--config", path)
    assert worker.zenoh_config == "/etc/z.json5" and worker.model == "/m.npz"


def test_environment_names_the_file(tmp_path, monkeypatch):
    path = write(tmp_path, '[driver]\nsource = "synthetic"\ncell = "envcell"\n')
    monkeypatch.setenv(config_file.CONFIG_ENV, str(path))
    assert parse("driver").cell == "envcell"


def test_flag_store_false(tmp_path):
    path = write(tmp_path, '[driver]\nsource = "synthetic"\nas-fast-as-possible = true\n')
    assert parse("driver", "--config", path).realtime is False


@pytest.mark.parametrize(
    "text, says",
    [
        ('[driver]\nsource = "synthetic"\nsorce = "x"\n', "cam.toml:3: unknown option 'sorce'"),
        ('[driver]\nsource = "synthetic"\nfps = "fast"\n', "cam.toml:3: fps: expected a number"),
        ('[driver]\nsource = "synthetic"\nloop = 1\n', "loop: expected true or false"),
        ('[driver]\nsource = "synthetic"\ncongestion = "slow"\n', "'slow' is not one of"),
        ('[drivr]\nsource = "synthetic"\n', "cam.toml:1: unknown table [drivr]"),
        ('[zenoh]\nport = 1\n[driver]\nsource = "s"\n', "cam.toml:2: unknown key 'port'"),
        ('source = "synthetic"\n', "must be inside a table such as [driver]"),
        ('[driver]\nsource = "synthetic\n', "cam.toml:2:"),
    ],
)
def test_bad_config_is_one_line_with_file_and_line(tmp_path, text, says):
    path = write(tmp_path, text)
    with pytest.raises(TopsegError) as err:
        parse("driver", "--config", path)
    message = str(err.value)
    assert says in message and "\n" not in message, message


def test_missing_file(tmp_path):
    with pytest.raises(TopsegError, match="does not exist"):
        parse("driver", "--config", tmp_path / "nope.toml")


def test_main_prints_the_line_and_exits_2(tmp_path, capsys):
    path = write(tmp_path, '[driver]\nsource = "synthetic"\nsorce = 1\n')
    assert cli.main(["driver", "--config", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("topseg driver: error: ") and "did you mean 'source'" in err
    assert len(err.splitlines()) == 1
