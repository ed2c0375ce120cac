"""io/gnss_source.py: the MAVLink telemetry log and the ArduPilot dataflash readers are GnssSources, and give the
fixes their own readers give."""

from conftest import shared_data

from photogram_ros.io.gnss_source import GnssSource, open_gnss_source


def test_a_tlog_is_a_gnss_source_with_the_node_s_fixes():
    from photogram_ros.io.mavlink import fixes_from_messages, read_tlog
    from photogram_ros.io.mavlink_ingest import TlogFixes
    path = shared_data('mavlink', 'sitl_vtol.tlog')
    src = open_gnss_source(path)
    assert isinstance(src, TlogFixes) and isinstance(src, GnssSource)
    got = list(src.fixes())
    events, _ = fixes_from_messages(read_tlog(path)[0])
    want = [ev.fix for ev in events if ev.best]
    assert len(got) == len(want) > 10
    assert [(f.t_s, f.lat_deg, f.fix_type) for f in got] == [(f.t_s, f.lat_deg, f.fix_type) for f in want]
    c = src.counts()
    assert c['fixes'] == len(got) and c['packets'] > 0


def test_a_dataflash_log_is_a_gnss_source_with_its_reader_s_fixes():
    from photogram_ros.io.dataflash import DataflashFixes, read_dataflash_fixes
    path = shared_data('mavlink', 'flightdata_center_0003.bin')
    src = open_gnss_source(path)
    assert isinstance(src, DataflashFixes) and isinstance(src, GnssSource)
    got = list(src.fixes())
    want, counts = read_dataflash_fixes(path)
    assert len(got) == len(want) > 10
    assert [(f.t_s, f.lat_deg, f.h_m) for f in got] == [(f.t_s, f.lat_deg, f.h_m) for f in want]
    assert src.counts() == dict(counts) and src.counts()['GPS'] >= len(got)


def test_what_is_not_a_gnss_source():
    class NoCounts:
        name = 'x'

        def fixes(self):
            return iter(())
    assert not isinstance(NoCounts(), GnssSource)


def test_a_trajectory_and_an_mrk_are_gnss_sources_of_their_epochs_as_the_one_fix_type():
    from pathlib import Path

    import numpy as np

    from photogram_ros.core.exposure_positions import gps_s_to_utc_unix
    from photogram_ros.core.gnss_fix import GnssFix
    from photogram_ros.core.geodesy import ecef_to_geodetic
    from photogram_ros.io.gnss_source import TrackFixes
    from photogram_ros.io.trajectory_formats import read_trajectory
    here = Path(__file__).parent / 'data' / 'trajectories'
    for name in ('waypoint_m300_5hz.txt', 'rtklib_demo5_5hz.pos', 'emlid_studio_5hz.csv', 'tbc_5hz.csv'):
        src = open_gnss_source(here / name)
        assert isinstance(src, TrackFixes) and isinstance(src, GnssSource), name
        got = list(src.fixes())
        track = read_trajectory(here / name, require_fix=False)
        assert len(got) == len(track) > 100 and all(isinstance(f, GnssFix) for f in got)
        k = len(got) // 2
        lat, lon, h = ecef_to_geodetic(*track.ecef_m[k])
        assert (got[k].lat_deg, got[k].lon_deg, got[k].h_m) == (float(lat), float(lon), float(h))
        assert got[k].quality == int(track.q[k]) and got[k].height_datum == 'ellipsoid'
        assert abs(got[k].stamp_ns * 1e-9 - gps_s_to_utc_unix(track.t_gps_s[k])) < 1e-6
        assert np.array_equal(got[k].cov_enu_m2, track.cov_enu_m2[k])
        assert src.counts()['epochs'] == len(got) and src.counts()['format'] == track.format
    mrk = open_gnss_source(here / 'm300_Timestamp.MRK')
    fixes = list(mrk.fixes())
    assert isinstance(mrk, TrackFixes) and len(fixes) >= 20
    assert fixes[0].native_scale == 'DJI Timestamp.MRK' and fixes[0].quality_native == 50 and fixes[0].quality == 1
