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
