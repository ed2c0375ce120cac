"""`--event-delay-ms` on a 5 Hz track at 12 m/s with a 30 ms shutter delay (issue #45), without the simulator's
rendering: a track parked until take-off, then at once at 12 m/s on a line, a 100 m radius turn and a line, like
`simulate --ppk`'s flight. The delay takes every exposure on the lines and in the turn back onto the truth; at the
take-off's instant speed step no interpolation of the 5 Hz epochs can (the product equals an independent linear
interpolation of them there), and bench/ppk_formats.py's split names those photos apart."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from photogram_ros.core.exposure_positions import ExposureOptions, utc_unix_to_gps_s
from photogram_ros.core.geodesy import LocalFrame
from photogram_ros.io.camera_events import write_mrk
from photogram_ros.io.geotag import GeotagInput, geotag
from photogram_ros.io.rtklib_pos import write_pos

ROOT = Path(__file__).resolve().parent.parent
T0_UNIX_S = 1_780_000_000.0
SPEED_MPS = 12.0
LINE_S = 5.0
TURN_RADIUS_M = 100.0
DELAY_S = 0.030
OFFSET_NED_M = np.array([0.05, -0.03, 0.21])       # antenna -> camera (N, E, V down), as a DJI MRK states it
FRAME = LocalFrame(47.0, 8.0, 500.0)


def antenna_enu(t_s: float) -> np.ndarray:
    """The true antenna: parked before t = 0, then 12 m/s east for LINE_S, a left turn of radius
    TURN_RADIUS_M for LINE_S (1.44 m/s^2), then straight on along the turn's last heading."""
    h = 60.0
    if t_s <= 0:
        return np.array([0.0, 0.0, h])
    if t_s <= LINE_S:
        return np.array([SPEED_MPS * t_s, 0.0, h])
    a_end = SPEED_MPS * LINE_S / TURN_RADIUS_M
    centre = np.array([SPEED_MPS * LINE_S, TURN_RADIUS_M])
    if t_s <= 2 * LINE_S:
        a = SPEED_MPS * (t_s - LINE_S) / TURN_RADIUS_M
        return np.array([*(centre + TURN_RADIUS_M * np.array([np.sin(a), -np.cos(a)])), h])
    end = centre + TURN_RADIUS_M * np.array([np.sin(a_end), -np.cos(a_end)])
    return np.array([*(end + SPEED_MPS * (t_s - 2 * LINE_S) * np.array([np.cos(a_end), np.sin(a_end)])), h])


def _flight(tmp_path: Path):
    """A 5 Hz .pos of the true antenna (epochs at odd tenths of a second) and an MRK of exposures every 0.4 s
    (even tenths: each halfway between two epochs), their marks DELAY_S before the exposures."""
    t_pos = np.arange(-1.1, 3 * LINE_S + 0.3, 0.2)
    llh = np.array([FRAME.enu_to_geodetic(antenna_enu(t)) for t in t_pos])
    gps = [utc_unix_to_gps_s(T0_UNIX_S + t) for t in t_pos]
    write_pos(tmp_path / 'flight.pos', gps, llh[:, 0], llh[:, 1], llh[:, 2], np.ones(len(gps), int),
              np.full((len(gps), 3), 0.01))
    t_exp = np.round(np.arange(0.0, 3 * LINE_S, 0.4), 6)
    cam = np.array([antenna_enu(t) + np.array([OFFSET_NED_M[1], OFFSET_NED_M[0], -OFFSET_NED_M[2]]) for t in t_exp])
    marks = [utc_unix_to_gps_s(T0_UNIX_S + t) - DELAY_S for t in t_exp]
    a_llh = np.array([FRAME.enu_to_geodetic(antenna_enu(t)) for t in t_exp])
    write_mrk(tmp_path / 'Timestamp.MRK', marks, np.tile(OFFSET_NED_M, (len(t_exp), 1)), a_llh[:, 0], a_llh[:, 1],
              a_llh[:, 2], [(2.0, 2.0, 4.0)] * len(t_exp), flag=16)
    return t_pos, t_exp, cam


def _errors(tmp_path: Path, delay_s: float, how: str, cam: np.ndarray) -> np.ndarray:
    res = geotag(GeotagInput(str(tmp_path / 'flight.pos'), str(tmp_path / 'Timestamp.MRK'), None,
                             str(tmp_path / 'geo.txt'), options=ExposureOptions(event_delay_s=delay_s,
                                                                                interpolation=how)))
    assert len(res.rows) == len(cam)
    ours = np.array([FRAME.geodetic_to_enu(pe.lat_deg, pe.lon_deg, pe.h_m) for _, pe in res.rows])
    return ours - cam


def test_event_delay_takes_a_30ms_shutter_back_on_lines_and_turns(tmp_path):
    t_pos, t_exp, cam = _flight(tmp_path)
    moving = t_exp > 0.5
    e0 = np.linalg.norm(_errors(tmp_path, 0.0, 'linear', cam), axis=1)
    # 30 ms at 12 m/s: 36 cm along the track without the delay
    assert np.all(np.abs(e0[moving] - SPEED_MPS * DELAY_S) < 0.005), e0
    turn = (t_exp > LINE_S + 0.5) & (t_exp < 2 * LINE_S - 0.5)
    line = moving & ~turn & (np.abs(t_exp - LINE_S) > 0.5) & (np.abs(t_exp - 2 * LINE_S) > 0.5)
    for how in ('linear', 'cubic'):
        e = np.linalg.norm(_errors(tmp_path, DELAY_S, how, cam), axis=1)
        print(f'{how}: line max {e[line].max() * 1000:.2f} mm, turn max {e[turn].max() * 1000:.2f} mm, '
              f'take-off {e[0] * 1000:.1f} mm')
        assert e[line].max() < 1e-3
        # a 1.44 m/s^2 turn: linear interpolation of 0.2 s epochs cuts it by a dt^2 / 8 = 7.2 mm at most
        assert e[turn].max() < (0.0075 if how == 'linear' else 1e-3)
        assert np.all(e[moving] < 0.01)


def test_at_the_take_off_step_the_product_is_the_interpolation_of_the_epochs(tmp_path):
    """At t = 0 the track goes from parked to 12 m/s at once: halfway between the epochs at -0.1 and 0.1 s a
    linear interpolation is 0.6 m ahead of the truth. geotag with the delay is that interpolation, to 1 mm."""
    t_pos, t_exp, cam = _flight(tmp_path)
    e = _errors(tmp_path, DELAY_S, 'linear', cam)
    ant_pos = np.array([antenna_enu(t) for t in t_pos])
    lin = np.array([np.interp(0.0, t_pos, ant_pos[:, k]) for k in range(3)])
    expected = lin - antenna_enu(0.0)
    assert abs(np.linalg.norm(expected) - 0.6) < 0.01
    assert np.linalg.norm(e[0] - expected) < 1e-3


def test_bench_split_names_the_speed_step_photos_apart(tmp_path):
    """bench/ppk_formats.py's split: the truth's acceleration around each exposure (sampled at 5 Hz on the whole
    tenths, as the simulator's fixes) puts the take-off photo apart; every photo a second or more from the step
    is smooth, and those are within 1 cm with the delay."""
    sys.path.insert(0, str(ROOT / 'bench'))
    try:
        import ppk_formats
    finally:
        sys.path.pop(0)
    t_pos, t_exp, cam = _flight(tmp_path)
    t_truth = np.round(np.arange(-1.0, 3 * LINE_S + 1.0, 0.2), 6)
    acc = ppk_formats.truth_acceleration_mps2(t_exp, t_truth, np.array([antenna_enu(t) for t in t_truth]))
    assert acc[0] > ppk_formats.SPEED_STEP_MPS2
    assert np.all(acc[t_exp >= 1.0] <= ppk_formats.SPEED_STEP_MPS2)
    e = np.linalg.norm(_errors(tmp_path, DELAY_S, 'linear', cam), axis=1)
    row = ppk_formats.split_by_motion(e, acc)
    assert row['photos'] == len(e) and row['max_m'] > 0.5             # every photo: the take-off's 0.6 m
    assert row['smooth_max_m'] < 0.01 and row['speed_step_max_m'] > 0.5
    assert row['smooth_photos'] + row['speed_step_photos'] == len(e)
    assert row['line_max_m'] < 1e-3
