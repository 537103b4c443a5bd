"""The obstacle picture: DISTANCE_SENSOR and OBSTACLE_DISTANCE folded into eight body sectors (hand-computed)."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rover_bridge.command.obstacles import (
    MAV_FRAME_BODY_FRD,
    MAV_FRAME_LOCAL_NED,
    UINT16_MAX,
    ObstaclePicture,
    SectorState,
    sector_bearing_ccw_rad,
    sector_of_cw_deg,
)
from rover_bridge.mavlink.dialect import mavlink

LIDAR = (1, 195, 0)
SONAR = (1, 158, 1)


def test_sector_ids_are_mavlink_yaw_rotations_turned_counter_clockwise() -> None:
    assert sector_bearing_ccw_rad(0) == 0.0
    assert sector_bearing_ccw_rad(1) == pytest.approx(-math.pi / 4)  # YAW_45: front right
    assert sector_bearing_ccw_rad(2) == pytest.approx(-math.pi / 2)  # YAW_90: right
    assert abs(sector_bearing_ccw_rad(4)) == pytest.approx(math.pi)  # YAW_180: behind
    assert sector_bearing_ccw_rad(6) == pytest.approx(math.pi / 2)  # YAW_270: left
    assert sector_bearing_ccw_rad(7) == pytest.approx(math.pi / 4)  # YAW_315: front left
    assert [sector_of_cw_deg(a) for a in (0.0, 22.4, 22.5, 67.4, 90.0, 337.5, 359.0, -10.0)] == [0, 0, 1, 1, 2, 0, 0, 0]


def test_distance_sensor_marks_its_sector_with_distance_and_age() -> None:
    pic = ObstaclePicture()
    pic.distance_sensor(10.0, LIDAR, 6, 350, 20, 1200)
    view = pic.view(10.25)
    left = view.sectors[6]
    assert left.state is SectorState.OBSTACLE
    assert left.distance_m == pytest.approx(3.5)
    assert left.bearing_ccw_rad == pytest.approx(math.pi / 2)
    assert left.age_s == pytest.approx(0.25)
    assert [s.state for i, s in enumerate(view.sectors) if i != 6] == [SectorState.UNKNOWN] * 7
    assert view.obstacles == (left,)


def test_out_of_range_high_is_clear_below_min_resets_the_sector() -> None:
    pic = ObstaclePicture()
    pic.distance_sensor(0.0, LIDAR, 0, 1201, 20, 1200)
    assert pic.view(0.0).sectors[0].state is SectorState.CLEAR
    pic.distance_sensor(0.1, LIDAR, 0, 300, 20, 1200)
    assert pic.view(0.1).sectors[0].distance_m == pytest.approx(3.0)
    pic.distance_sensor(0.2, LIDAR, 0, 10, 20, 1200)  # below min: ArduPilot resets the face
    assert pic.view(0.2).sectors[0].state is SectorState.UNKNOWN
    pic.distance_sensor(0.3, LIDAR, 0, 0, 0, 1200)  # zero is never a distance
    assert pic.view(0.3).sectors[0].state is SectorState.UNKNOWN
    assert (pic.counts.readings, pic.counts.out_of_range_high, pic.counts.below_min) == (4, 1, 2)


def test_pitch_and_roll_orientations_are_ignored_and_counted() -> None:
    pic = ObstaclePicture()
    for orientation in (8, 24, 25, 100):  # ROLL_180, PITCH_90 (up), PITCH_270 (down), CUSTOM
        pic.distance_sensor(0.0, SONAR, orientation, 100, 20, 700)
    view = pic.view(0.0)
    assert pic.counts.ignored_orientation == 4
    assert all(s.state is SectorState.UNKNOWN for s in view.sectors)
    assert pic.view(5.0).silent_sensors == ()  # never seen as a proximity sensor: never reported silent


def test_a_reading_ages_out_after_the_face_timeout() -> None:
    pic = ObstaclePicture(face_timeout_s=1.0)
    pic.distance_sensor(0.0, LIDAR, 0, 300, 20, 1200)
    assert pic.view(0.99).sectors[0].state is SectorState.OBSTACLE
    assert pic.view(1.01).sectors[0].state is SectorState.UNKNOWN


def test_a_sensor_seen_then_silent_is_reported_until_it_speaks_again() -> None:
    pic = ObstaclePicture(sensor_timeout_s=0.5)
    pic.distance_sensor(0.0, LIDAR, 0, 300, 20, 1200)
    pic.distance_sensor(0.0, SONAR, 4, 300, 20, 700)
    assert not pic.view(0.45).blind
    pic.distance_sensor(0.5, SONAR, 4, 300, 20, 700)
    view = pic.view(0.6)
    assert view.blind and view.silent_sensors == (LIDAR,)
    pic.distance_sensor(0.7, LIDAR, 0, 300, 20, 1200)
    assert not pic.view(0.8).blind


def test_the_nearest_fresh_obstacle_of_several_sensors_wins() -> None:
    pic = ObstaclePicture()
    pic.distance_sensor(0.0, LIDAR, 0, 500, 20, 1200)
    pic.distance_sensor(0.0, SONAR, 0, 250, 20, 700)
    assert pic.view(0.0).sectors[0].distance_m == pytest.approx(2.5)
    pic.distance_sensor(0.1, SONAR, 0, 701, 20, 700)  # the sonar now sees nothing: the lidar's 5 m stands
    assert pic.view(0.1).sectors[0].distance_m == pytest.approx(5.0)
    pic.distance_sensor(0.2, LIDAR, 0, 1300, 20, 1200)
    assert pic.view(0.2).sectors[0].state is SectorState.CLEAR


def scan(fill: int = 1201) -> list[int]:
    return [fill] * 72


def test_obstacle_distance_folds_72_elements_into_sectors_at_the_closest_bearing() -> None:
    d = scan()
    d[0], d[1] = 250, 240  # 0 and 5 degrees right: sector 0, closest at 5 degrees right
    for j in range(5, 14):  # 25..65 degrees: all of sector 1 unknown
        d[j] = UINT16_MAX
    d[50] = 150  # 250 degrees, below min; the rest of sector 6 sees nothing
    pic = ObstaclePicture()
    pic.obstacle_distance(0.0, LIDAR, d, 5, 0.0, 0.0, 200, 1200, MAV_FRAME_BODY_FRD, None)
    view = pic.view(0.0)
    assert view.sectors[0].state is SectorState.OBSTACLE
    assert view.sectors[0].distance_m == pytest.approx(2.4)
    assert view.sectors[0].bearing_ccw_rad == pytest.approx(math.radians(-5.0))
    assert view.sectors[1].state is SectorState.UNKNOWN
    assert view.sectors[6].state is SectorState.CLEAR
    assert [s.state for s in view.sectors[2:6]] == [SectorState.CLEAR] * 4
    assert pic.counts.below_min == 1 and pic.counts.out_of_range_high == 72 - 2 - 9 - 1


def test_obstacle_distance_unknown_elements_keep_the_old_reading_until_it_ages_out() -> None:
    pic = ObstaclePicture()
    d = scan()
    d[0] = 300
    pic.obstacle_distance(0.0, LIDAR, d, 5, 0.0, 0.0, 20, 1200, MAV_FRAME_BODY_FRD, None)
    d = scan()
    for j in (68, 69, 70, 71, 0, 1, 2, 3, 4):  # all of sector 0 (-20..20 degrees)
        d[j] = UINT16_MAX
    pic.obstacle_distance(0.5, LIDAR, d, 5, 0.0, 0.0, 20, 1200, MAV_FRAME_BODY_FRD, None)
    front = pic.view(0.5).sectors[0]
    assert front.state is SectorState.OBSTACLE and front.age_s == pytest.approx(0.5)
    assert pic.view(1.1).sectors[0].state is SectorState.UNKNOWN


def test_obstacle_distance_increment_f_offset_and_element_count() -> None:
    pic = ObstaclePicture()
    d = scan()
    d[0] = 300  # at the offset: 90 degrees right
    d[40] = 100  # past 360 / 10 = 36 elements: not read
    pic.obstacle_distance(0.0, LIDAR, d, 5, 10.0, 90.0, 20, 1200, MAV_FRAME_BODY_FRD, None)
    view = pic.view(0.0)
    assert [s.index for s in view.obstacles] == [2]
    assert view.sectors[2].bearing_ccw_rad == pytest.approx(-math.pi / 2)
    pic.obstacle_distance(0.0, SONAR, d, 0, 0.0, 0.0, 20, 1200, MAV_FRAME_BODY_FRD, None)
    assert pic.counts.bad_increment == 1


def test_obstacle_distance_in_an_earth_frame_needs_the_heading() -> None:
    d = scan()
    d[18] = 300  # 90 degrees clockwise from north: east
    pic = ObstaclePicture()
    pic.obstacle_distance(0.0, LIDAR, d, 5, 0.0, 0.0, 20, 1200, MAV_FRAME_LOCAL_NED, None)
    assert pic.counts.no_heading == 1 and pic.view(0.0).obstacles == ()
    pic.obstacle_distance(0.0, LIDAR, d, 5, 0.0, 0.0, 20, 1200, MAV_FRAME_LOCAL_NED, math.pi / 2)  # facing east
    front = pic.view(0.0).sectors[0]
    assert front.state is SectorState.OBSTACLE and front.bearing_ccw_rad == pytest.approx(0.0, abs=1e-9)
    pic.obstacle_distance(0.0, SONAR, d, 5, 0.0, 0.0, 20, 1200, 8, None)  # BODY_NED: not a frame for scans
    assert pic.counts.ignored_frame == 1


def test_pymavlink_messages_feed_the_picture() -> None:
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=195)
    pic = ObstaclePicture()
    ds = mav.distance_sensor_encode(0, 20, 1200, 300, 0, 7, 2, 0)  # YAW_90: right, 3 m
    ds.pack(mav)  # sets the header: the sender is (1, 195), sensor id 7
    assert pic.handle(ds, 0.0)
    d = scan()
    d[0] = 250
    od = mav.obstacle_distance_encode(0, 0, d, 5, 20, 1200, 0.0, 0.0, MAV_FRAME_BODY_FRD)
    od.pack(mav)
    assert pic.handle(od, 0.0)
    assert not pic.handle(mav.heartbeat_encode(6, 8, 0, 0, 0), 0.0)
    view = pic.view(0.0)
    assert view.sectors[2].distance_m == pytest.approx(3.0)
    assert view.sectors[2].bearing_ccw_rad == pytest.approx(-math.pi / 2)
    assert view.sectors[0].distance_m == pytest.approx(2.5)
    assert pic.view(0.6).silent_sensors == ((1, 195, 0), (1, 195, 7))


# The picture keeps each sector's winner from one reading to the next (the limiter asks every output): asking at
# many times must say exactly what a picture asked once would, and `near` what `view` says with the ageing applied.
_reading = st.tuples(st.floats(0.0, 0.3), st.sampled_from([LIDAR, SONAR]), st.integers(0, 7),
                     st.integers(0, 1500))


@settings(max_examples=150, deadline=None)
@given(st.lists(_reading, min_size=1, max_size=25), st.lists(st.floats(0.0, 2.5), min_size=1, max_size=6),
       st.floats(0.0, 2.0))
def test_asking_often_says_what_asking_once_would(readings: list[tuple[float, tuple[int, int, int], int, int]],
                                                  probes: list[float], closing_m_s: float) -> None:
    often = ObstaclePicture()
    t = 0.0
    fed: list[tuple[float, tuple[int, int, int], int, int]] = []
    for gap_s, sensor, orientation, cm in readings:
        t += gap_s
        for probe in sorted(p for p in probes if fed and fed[-1][0] <= p < t):
            assert_same(often, fed, probe, closing_m_s)
        often.distance_sensor(t, sensor, orientation, cm, 20, 1200)
        fed.append((t, sensor, orientation, cm))
    for probe in sorted(t + p for p in probes):
        assert_same(often, fed, probe, closing_m_s)


def assert_same(often: ObstaclePicture, fed: list[tuple[float, tuple[int, int, int], int, int]], now_s: float,
                closing_m_s: float) -> None:
    once = ObstaclePicture()
    for t, sensor, orientation, cm in fed:
        once.distance_sensor(t, sensor, orientation, cm, 20, 1200)
    assert often.view(now_s) == once.view(now_s)
    aged = tuple((s.index, s.bearing_ccw_rad, s.distance_m - closing_m_s * s.age_s)
                 for s in once.view(now_s).obstacles if s.distance_m is not None and s.age_s is not None)
    near = often.near(now_s, closing_m_s)
    assert sorted((s.index, s.bearing_ccw_rad, s.distance_m) for s in near.sectors) == sorted(aged)
    assert near.silent_sensors == once.view(now_s).silent_sensors
