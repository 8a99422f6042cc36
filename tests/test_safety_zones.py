"""Zones in the image: the pixels whose ray passes through a zone's prism (checked by hand and
against a dense sampling of each ray), the zones a person is in, and the unseen rule."""

from __future__ import annotations

import numpy as np
import pytest

from topseg.core.camera import NO_READING_MM, Intrinsics, TopViewMount
from topseg.core.safety.cell import CameraPlacement, Zone
from topseg.core.safety.zones import (
    occupied_zones,
    pixel_rays_cell,
    points_in_polygon,
    unseen_fraction,
    zone_masks,
)

K = Intrinsics(64, 48, 40.0, 40.0, 31.5, 23.5)
DOWN = TopViewMount(K, 3000.0)  # straight down, 3 m above the floor
ORIGIN = CameraPlacement()
PILLAR = Zone("pillar", "protective", ((1.0, -0.1), (1.2, -0.1), (1.2, 0.1), (1.0, 0.1)), 0, 2)


def sampled_mask(zone: Zone, mount: TopViewMount, placement: CameraPlacement) -> np.ndarray:
    """The reference: each pixel's ray sampled at 801 heights through the zone's range."""
    centre, directions = pixel_rays_cell(mount, placement)
    d = directions.reshape(-1, 3)
    hit = np.zeros(len(d), bool)
    polygon = np.asarray(zone.polygon_m)
    for z in np.linspace(zone.z_min_m, zone.z_max_m, 801):
        t = (z - centre[2]) / d[:, 2]
        ahead = t >= 0
        xy = centre[:2] + t[:, None] * d[:, :2]
        hit |= ahead & points_in_polygon(xy, polygon)
    return hit.reshape(K.shape)


def test_pillar_worked_by_hand():
    # straight down from 3 m, a pixel's ray is at x = (3 - z) (u - cx) / fx: it passes
    # through x in [1.0, 1.2] between z = 0 and 2 when (u - cx) / fx is in [1/3, 1.2]:
    # u >= 44.83 (the floor footprint alone would stop at u = 47)
    (mask,) = zone_masks((PILLAR,), DOWN, ORIGIN).masks
    row = mask[24]
    assert not row[:45].any()
    assert row[45:].all()
    assert not mask[0].any() and not mask[-1].any()


def test_masks_match_a_dense_sampling_of_each_ray_with_tilt_and_placement():
    mount = TopViewMount(K, 3200.0, pitch_deg=15.0, roll_deg=-8.0)
    placement = CameraPlacement("cam0", x_m=1.0, y_m=2.0, yaw_deg=30.0)
    concave = Zone(
        "l-shape", "warning", ((0.5, 1.5), (2.0, 1.5), (2.0, 2.0), (1.0, 2.0), (1.0, 3.0),
                               (0.5, 3.0)), 0.3, 1.8,
    )  # fmt: skip
    (exact,) = zone_masks((concave,), mount, placement).masks
    sampled = sampled_mask(concave, mount, placement)
    assert sampled.any() and not sampled.all()
    assert not (sampled & ~exact).any()  # every sampled hit is found
    assert (exact & ~sampled).sum() <= 0.02 * exact.sum()  # extra only where a ray grazes


def test_placement_moves_the_zone_with_the_camera():
    placement = CameraPlacement("cam0", x_m=1.0, y_m=2.0, yaw_deg=90.0)
    corners = np.array([[x, y, 0.0] for x, y in PILLAR.polygon_m])
    moved = Zone(
        "pillar",
        "protective",
        tuple(tuple(p[:2]) for p in placement.to_cell(corners)),
        PILLAR.z_min_m,
        PILLAR.z_max_m,
    )
    here = zone_masks((PILLAR,), DOWN, ORIGIN).masks[0]
    there = zone_masks((moved,), DOWN, placement).masks[0]
    np.testing.assert_array_equal(here, there)


def test_zone_reaching_above_the_camera():
    tall = Zone("all", "protective", ((-0.5, -0.5), (0.5, -0.5), (0.5, 0.5), (-0.5, 0.5)), 0, 9)
    (mask,) = zone_masks((tall,), DOWN, ORIGIN).masks
    assert mask.all()  # every ray starts inside the prism, at the camera


def test_occupied_zones():
    masks = zone_masks((PILLAR,), DOWN, ORIGIN)
    inside = np.array([[1.1, 0.0, 1.0]])
    above = np.array([[1.1, 0.0, 2.5]])
    beside = np.array([[0.5, 0.0, 1.0]])
    assert occupied_zones(masks, inside) == ["pillar"]
    assert occupied_zones(masks, above) == []
    assert occupied_zones(masks, beside) == []
    assert occupied_zones(masks, np.vstack([inside, inside]), min_points=3) == []
    assert occupied_zones(masks, np.empty((0, 3))) == []


def test_a_person_pixel_without_depth_holds_the_zones_it_looks_through():
    masks = zone_masks((PILLAR,), DOWN, ORIGIN)
    lost = np.array([[np.nan, np.nan, np.nan]])
    assert occupied_zones(masks, lost) == []  # no pixel: nothing known
    assert occupied_zones(masks, lost, np.array([[24, 50]])) == ["pillar"]
    assert occupied_zones(masks, lost, np.array([[24, 10]])) == []
    with pytest.raises(ValueError, match="2 pixels for 1 points"):
        occupied_zones(masks, lost, np.array([[24, 50], [1, 1]]))


def test_unseen_fraction_counts_holes_the_robot_does_not_explain():
    warn = Zone("w", "warning", PILLAR.polygon_m, 0, 2)
    masks = zone_masks((PILLAR, warn), DOWN, ORIGIN)
    zone_pixels = masks.mask("pillar")
    n = int(zone_pixels.sum())
    depth = np.full(K.shape, 2500, np.uint16)
    rows, cols = np.nonzero(zone_pixels)
    depth[rows[:4], cols[:4]] = 0
    depth[rows[4:6], cols[4:6]] = NO_READING_MM
    assert unseen_fraction(masks, depth, None) == {"pillar": pytest.approx(6 / n)}
    shadow = np.zeros(K.shape, bool)
    shadow[rows[:3], cols[:3]] = True  # the robot explains three of the holes
    assert unseen_fraction(masks, depth, shadow) == {"pillar": pytest.approx(3 / n)}


def test_a_zone_out_of_view_is_wholly_unseen():
    far = Zone("far", "protective", ((9, 9), (10, 9), (10, 10)), 0, 2)
    masks = zone_masks((far,), DOWN, ORIGIN)
    assert unseen_fraction(masks, np.full(K.shape, 2500, np.uint16), None) == {"far": 1.0}


def test_unseen_fraction_refuses_frames_of_another_size():
    masks = zone_masks((PILLAR,), DOWN, ORIGIN)
    with pytest.raises(ValueError, match="zone masks"):
        unseen_fraction(masks, np.zeros((10, 10), np.uint16), None)
    with pytest.raises(ValueError, match="robot_shadow_mask"):
        unseen_fraction(masks, np.zeros(K.shape, np.uint16), np.zeros((2, 2), bool))


def test_zone_samples_fill_the_prism_up_to_head_height():
    from topseg.core.safety.zones import MAX_SAMPLE_HEIGHT_M, zone_samples

    zone = Zone("z", "protective", ((0.0, 0.0), (1.0, 0.0), (0.0, 1.0)), 0.0, 3.0)
    pts = zone_samples(zone)
    assert set(np.round(pts[:, 2], 6)) == {0.0, MAX_SAMPLE_HEIGHT_M / 2, MAX_SAMPLE_HEIGHT_M}
    assert points_in_polygon(pts[:, :2], np.array(zone.polygon_m)).all()
    assert len(pts) == 3 * len(pts[pts[:, 2] == 0.0]) > 3 * 150  # a 5 cm grid over 0.5 m2


def test_a_zone_is_unseen_where_no_camera_looking_at_it_has_depth():
    """Two cameras, a zone running from one's view into the other's: the other going blind
    leaves the part only it looks at unseen, whatever the first sees of its own part."""
    from topseg.core.safety.separation import camera_pixels
    from topseg.core.safety.zones import unseen_by_all, zone_samples

    zone = Zone("long", "protective", ((1.5, -0.2), (3.5, -0.2), (3.5, 0.2), (1.5, 0.2)), 0, 2)
    a, b = ORIGIN, CameraPlacement(name="b", x_m=3.0)
    pts = zone_samples(zone)
    clear, blind = np.zeros(K.shape, bool), np.ones(K.shape, bool)
    in_a = camera_pixels(pts, DOWN, a)[2]
    in_b = camera_pixels(pts, DOWN, b)[2]
    assert in_a.any() and in_b.any() and (in_b & ~in_a).any()
    assert unseen_by_all(pts, [(DOWN, a, clear), (DOWN, b, clear)]) == 0.0
    only_b = (in_b & ~in_a).sum() / (in_a | in_b).sum()
    assert unseen_by_all(pts, [(DOWN, a, clear), (DOWN, b, blind)]) == pytest.approx(only_b)
    assert unseen_by_all(pts, [(DOWN, a, blind), (DOWN, b, blind)]) == 1.0
    far = CameraPlacement(name="far", x_m=40.0)
    assert unseen_by_all(pts, [(DOWN, far, clear)]) == 1.0  # nobody looks at it
