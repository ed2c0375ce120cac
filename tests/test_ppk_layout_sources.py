"""A GrafNav export in the UTM profile a public reader of real GrafNav files uses (columbia-glacier/gps-rovers-2010
scripts/process.R: a 20-line header, then `Date GPSTime Easting Northing H-Ell SDHoriz SDHeigh Q`, Date MM/DD/YYYY,
GPSTime HH:MM:SS; see tests/data/trajectories/LAYOUT_SOURCES.md): `geotag --pos` does not read grid coordinates,
and says so with what to export instead rather than placing photos wrongly."""

import pytest

from photogram_ros.errors import DataError
from photogram_ros.io.trajectory_formats import read_trajectory

HEADER = ['Project:     S1R1', 'Program:     GrafNav Version 8.10', 'Profile:     UTM'] + [''] * 17


def test_grafnav_utm_profile_is_refused_naming_the_profile_to_export(tmp_path):
    lines = HEADER + ['      Date     GPSTime      Easting      Northing      H-Ell  SDHoriz  SDHeigh  Q',
                      '05/14/2010  03:14:00   496000.123   6770000.456   123.456    0.012    0.020  1',
                      '05/14/2010  03:14:30   496001.123   6770001.456   123.556    0.012    0.020  1']
    assert len(HEADER) == 20                      # the column line is line 21, as in those exports
    p = tmp_path / 'S1R1.txt'
    p.write_text('\n'.join(lines) + '\n')
    with pytest.raises(DataError, match='Latitude/Longitude'):
        read_trajectory(p)


def test_the_same_export_with_latitude_longitude_is_read(tmp_path):
    lines = HEADER + ['      Date     GPSTime      Latitude       Longitude      H-Ell  SDHoriz  SDHeigh  Q',
                      '05/14/2010  03:14:00   61.1234567  -147.0123456   123.456    0.012    0.020  1',
                      '05/14/2010  03:14:30   61.1234667  -147.0123356   123.556    0.012    0.020  1']
    p = tmp_path / 'S1R1.txt'
    p.write_text('\n'.join(lines) + '\n')
    t = read_trajectory(p)
    assert t.format.startswith('NovAtel') and len(t) == 2 and t.time_system == 'GPST'
    assert t.t_gps_s[1] - t.t_gps_s[0] == pytest.approx(30.0)
