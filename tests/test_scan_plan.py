"""The scan plan is data: plates first, then every (elevation, azimuth) shot, each with its own file."""

import pytest

from station.capture.plan import ScanPlan, default_elevations
from station.errors import BadInputError

pytestmark = pytest.mark.no_kernels


def test_default_plan_is_six_by_forty_plus_one_plate_per_elevation():
    plan = ScanPlan()
    frames = plan.frames()
    assert len(plan.elevations_deg) == 6
    assert sum(f.kind == "shot" for f in frames) == 240
    assert sum(f.kind == "plate" for f in frames) == 6
    assert len({f.file for f in frames}) == 246


def test_plates_come_before_shots_and_shots_run_elevation_major():
    plan = ScanPlan(elevations_deg=(20.0, 50.0), azimuths=3)
    assert [(f.kind, f.elevation_deg, f.azimuth_deg) for f in plan.frames()] == [
        ("plate", 20.0, 0.0),
        ("plate", 50.0, 0.0),
        ("shot", 20.0, 0.0),
        ("shot", 20.0, 120.0),
        ("shot", 20.0, 240.0),
        ("shot", 50.0, 0.0),
        ("shot", 50.0, 120.0),
        ("shot", 50.0, 240.0),
    ]


def test_default_elevations_cover_the_upper_hemisphere_without_grazing_or_zenith():
    elevations = default_elevations(6)
    assert elevations[0] >= 5 and elevations[-1] <= 80
    assert list(elevations) == sorted(elevations)


def test_plan_round_trips_through_scan_json_dict():
    plan = ScanPlan(elevations_deg=(15.0, 45.0), azimuths=12, exposure_s=0.02, iso=200)
    assert ScanPlan.from_dict(plan.to_dict()) == plan


@pytest.mark.parametrize("kwargs", [{"azimuths": 0}, {"elevations_deg": ()}, {"elevations_deg": (95.0,)}, {"iso": 0}])
def test_impossible_plans_are_refused(kwargs):
    with pytest.raises(BadInputError, match="scan plan"):
        ScanPlan(**kwargs)
