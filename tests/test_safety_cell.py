"""The cell file: the example loads, every table is checked, and each bad file is one clear
ConfigError naming the file and the key."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from topseg.core import labels
from topseg.core.errors import ConfigError
from topseg.core.safety.cell import (
    DEFAULT_REGIONS,
    CameraPlacement,
    cell_from_dict,
    intrusion_distance_m,
    load_cell,
    polygon_problem,
)

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "deploy" / "config" / "cell1.cell.toml"

MINIMAL = 'cell = "c1"\n'
SQUARE = "[[0, 0], [1, 0], [1, 1], [0, 1]]"


def write(tmp_path: Path, text: str, name: str = "cell.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def refused(tmp_path: Path, text: str) -> str:
    """The one-line message of the ConfigError that loading `text` gives."""
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_cell(path)
    message = str(info.value)
    assert "\n" not in message
    assert str(path) in message
    return message


def test_example_cell_file_loads():
    cell = load_cell(EXAMPLE)
    assert cell.cell == "cell1" and cell.source == str(EXAMPLE)
    assert cell.robot is not None and cell.robot.urdf == "panda" and cell.robot.is_catalogue
    assert cell.robot.base_xyz_m == (1.5, 1.0, 0.0)
    assert [c.name for c in cell.cameras] == ["cam0"]
    assert {z.name: z.kind for z in cell.zones} == {
        "around-robot": "warning",
        "press": "protective",
    }
    # d = 40 mm gives ISO 13855's C = 8 (40 - 14) mm = 208 mm
    assert cell.separation.intrusion_m == pytest.approx(0.208)
    assert set(cell.regions) == set(labels.HUMAN_IDS)
    assert not cell.regions[labels.HEAD].contact_allowed


def test_minimal_cell_takes_the_defaults():
    cell = cell_from_dict({"cell": "c1"}, "mem")
    assert cell.robot is None and cell.zones == ()
    assert [c.name for c in cell.cameras] == ["cam0"]
    assert cell.regions == DEFAULT_REGIONS
    assert cell.separation.human_speed_mps == 1.6  # ISO 13855


def test_intrusion_distance_follows_iso_13855():
    assert intrusion_distance_m(14) == 0.0
    assert intrusion_distance_m(30) == pytest.approx(0.128)  # 8 * 16 mm
    assert intrusion_distance_m(40) == pytest.approx(0.208)
    assert intrusion_distance_m(70) == pytest.approx(0.850)  # body detection
    cell = cell_from_dict({"cell": "c", "separation": {"detection_capability_mm": 20}}, "m")
    assert cell.separation.intrusion_m == pytest.approx(0.048)
    cell = cell_from_dict({"cell": "c", "separation": {"intrusion_m": 0.3}}, "m")
    assert cell.separation.intrusion_m == 0.3


def test_relative_urdf_is_resolved_against_the_cell_files_folder(tmp_path):
    (tmp_path / "robots").mkdir()
    urdf = tmp_path / "robots" / "arm.urdf"
    urdf.write_text("<robot name='arm'/>")
    cell = load_cell(write(tmp_path, MINIMAL + '[robot]\nname = "arm"\nurdf = "robots/arm.urdf"\n'))
    assert cell.robot.urdf == str(urdf)
    assert not cell.robot.is_catalogue


def test_missing_urdf_file_is_named(tmp_path):
    message = refused(tmp_path, MINIMAL + '[robot]\nname = "arm"\nurdf = "nowhere/arm.urdf"\n')
    assert "[robot]" in message and "nowhere/arm.urdf" in message and "no such file" in message


def test_unknown_catalogue_robot_is_refused_with_a_suggestion(tmp_path):
    message = refused(tmp_path, MINIMAL + '[robot]\nname = "arm"\nurdf = "pand"\n')
    assert "did you mean 'panda'" in message


def test_region_table_replaces_only_its_keys(tmp_path):
    cell = load_cell(write(tmp_path, MINIMAL + "[regions.upper-arm]\nmax_force_n = 100\n"))
    region = cell.regions[labels.UPPER_ARM]
    assert region.max_force_n == 100.0
    assert region.effective_mass_kg == DEFAULT_REGIONS[labels.UPPER_ARM].effective_mass_kg


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        # wrong type
        (MINIMAL + "deadline_ms = 'soon'\n", "deadline_ms must be a number"),
        (MINIMAL + '[robot]\nname = "a"\nurdf = "panda"\nstopping_time_s = "0.5"\n',
         "[robot]: stopping_time_s must be a number"),
        # unknown keys, with a suggestion
        (MINIMAL + "dedline_ms = 100\n", "unknown key 'dedline_ms' (did you mean 'deadline_ms'?)"),
        (MINIMAL + '[robot]\nname = "a"\nurdf = "panda"\nstoping_time_s = 1\n',
         "unknown key 'stoping_time_s' (did you mean 'stopping_time_s'?)"),
        (MINIMAL + "[separation]\nhuman_speed = 2\n",
         "[separation]: unknown key 'human_speed' (did you mean 'human_speed_mps'?)"),
        # zones
        (MINIMAL + '[[zone]]\nname = "z"\nkind = "protective"\n'
         "polygon_m = [[0, 0], [1, 1], [1, 0], [0, 1]]\n",
         "[zone 'z']: polygon_m crosses itself"),
        (MINIMAL + f'[[zone]]\nname = "z"\nkind = "warning"\npolygon_m = {SQUARE}\n'
         "z_min_m = 2\nz_max_m = 1\n", "[zone 'z']: z_min_m (2) must be below z_max_m (1)"),
        (MINIMAL + f'[[zone]]\nname = "z"\nkind = "protect"\npolygon_m = {SQUARE}\n',
         "(did you mean 'protective'?)"),
        (MINIMAL + '[[zone]]\nname = "z"\nkind = "warning"\npolygon_m = [[0, 0], [1, 0]]\n',
         "polygon_m needs at least 3 vertices"),
        (MINIMAL + '[[zone]]\nname = "z"\nkind = "warning"\npolygon_m = [[0, 0], [1, 0], [2, 0]]\n',
         "polygon_m has no area"),
        (MINIMAL + f'[[zone]]\nname = "z"\nkind = "warning"\npolygon_m = {SQUARE}\n' * 2,
         "zone name 'z' is used twice"),
        # regions
        (MINIMAL + "[regions.hands]\nmax_force_n = 100\n",
         "unknown part 'hands' (did you mean 'hand'?)"),
        (MINIMAL + "[regions.chair]\nmax_force_n = 100\n", "unknown part 'chair'"),
        (MINIMAL + "[regions.head]\ncontact_allowed = true\n",
         "[regions.head]: contact_allowed must be false"),
        (MINIMAL + "[regions.hand]\nmax_force_n = -1\n", "max_force_n must be a positive"),
        # ranges and names
        (MINIMAL + "max_unseen_fraction = 1.5\n", "max_unseen_fraction must be within 0..1"),
        ('cell = "a/b"\n', "cell 'a/b' must be 1-64 characters"),
        ("deadline_ms = 10\n", "missing key 'cell'"),
        (MINIMAL + '[robot]\nname = "a"\nurdf = "panda"\njoints_source = "ros"\n',
         "joints_source must be one of zenoh, ros2"),
        (MINIMAL + '[robot]\nname = "a"\nurdf = "panda"\nmax_speed_mps = 0\n',
         "max_speed_mps must be a positive number"),
        (MINIMAL + '[robot]\nurdf = "panda"\n', "[robot]: missing key 'name'"),
        (MINIMAL + '[[camera]]\nname = "cam0"\nyaw_deg = nan\n', "yaw_deg must be a finite"),
        (MINIMAL + "cell = 'again'\n", "not valid TOML"),
    ],
)  # fmt: skip
def test_bad_cell_files_give_one_clear_error(tmp_path, text, expected):
    assert expected in refused(tmp_path, text)


def test_missing_file_is_named(tmp_path):
    with pytest.raises(ConfigError, match="no such cell file"):
        load_cell(tmp_path / "absent.toml")


@pytest.mark.parametrize(
    ("polygon", "simple"),
    [
        (((0, 0), (1, 0), (1, 1), (0, 1)), True),
        (((0, 0), (2, 0), (2, 2), (1, 1), (0, 2)), True),  # concave
        (((0, 0), (1, 1), (1, 0), (0, 1)), False),  # a bow tie
        (((0, 0), (2, 0), (2, 2), (0, 2), (1, 0)), False),  # a vertex on another edge
        (((0, 0), (1, 0), (1, 0), (0, 1)), False),  # a repeated vertex
    ],
)
def test_polygon_check(polygon, simple):
    assert (polygon_problem(polygon) is None) == simple


def test_camera_placement_turns_and_moves_points():
    placement = CameraPlacement("cam0", x_m=2.0, y_m=1.0, yaw_deg=90.0)
    world = np.array([[1.0, 0.0, 0.5], [0.0, 2.0, 0.0]])
    cell = placement.to_cell(world)
    # Rz(90) (1, 0) = (0, 1); Rz(90) (0, 2) = (-2, 0); then + (2, 1)
    np.testing.assert_allclose(cell, [[2.0, 2.0, 0.5], [0.0, 1.0, 0.0]], atol=1e-12)
    np.testing.assert_allclose(placement.to_camera_world(cell), world, atol=1e-12)
