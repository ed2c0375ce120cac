"""One rule for EXIF altitudes in the live graph and in triangulate (issue 47): camera_node's exif_altitude and
`triangulate --exif-altitude` read GPSAltitude alike (io/image_source.exif_altitude_reading; above mean sea level
by default, as the EXIF standard says, through core/geoid's EGM2008), a DJI XMP drone-dji:AbsoluteAltitude standing
in where the EXIF has no altitude; `replay` takes the same options as `triangulate`."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from conftest import shared_data
from photogram_ros.errors import ConfigError
from photogram_ros.io.image_source import exif_altitude_reading, read_dji_xmp, read_exif_gps
from photogram_ros.io.photo_block import exif_position
from test_camera_node import _listener, _spin_until
from test_triangulate_command import with_exif

BRIGHTON = shared_data('photos', 'brighton_beach', 'images')


def test_the_readings_and_their_checks():
    assert exif_altitude_reading('orthometric') == ('msl', None, 'msl')
    assert exif_altitude_reading('ellipsoidal', float('nan')) == ('ellipsoidal', None, 'msl')
    assert exif_altitude_reading('relative', 180.0, 'ellipsoidal') == ('relative', 180.0, 'ellipsoidal')
    with pytest.raises(ConfigError, match='take-off point need its height'):
        exif_altitude_reading('relative')
    with pytest.raises(ConfigError, match='only used with EXIF altitudes relative'):
        exif_altitude_reading('orthometric', 180.0)
    with pytest.raises(ConfigError, match='baro'):
        exif_altitude_reading('baro')


def test_a_dji_photo_without_gps_altitude_takes_its_xmp_absolute_altitude(tmp_path):
    from PIL import Image
    src = BRIGHTON / 'DJI_0018.JPG'
    with Image.open(src) as im:
        exif = im.getexif()
    gps = exif.get_ifd(0x8825)
    del gps[6]
    out = tmp_path / src.name
    out.write_bytes(with_exif(src.read_bytes(), exif))
    xmp_alt_m = float(read_dji_xmp(src)['AbsoluteAltitude'])
    assert xmp_alt_m == pytest.approx(198.31) and read_exif_gps(src).alt_msl_m == pytest.approx(198.309)
    assert read_exif_gps(out).alt_msl_m == pytest.approx(xmp_alt_m)
    # Through the same geoid: the heights of both readings 1 mm apart (the XMP rounds to centimetres).
    assert exif_position(out)[2] == pytest.approx(exif_position(src)[2], abs=0.002)


@pytest.mark.parametrize('reading, overrides', [
    (('msl',), {}),
    (('ellipsoidal',), {'exif_altitude': 'ellipsoidal'}),
    (('relative', 158.5, 'msl'), {'exif_altitude': 'relative', 'takeoff_altitude_m': 158.5}),
])
def test_camera_node_publishes_the_heights_triangulate_reads(reading, overrides, rclpy_context, tmp_path):
    """Three brighton photos through camera_node: each fix's height equals io/photo_block.exif_position's (what
    triangulate adjusts with) under the same reading."""
    from rclpy.executors import SingleThreadedExecutor

    from photogram_ros import msgs
    from photogram_ros.nodes.camera_node import CameraNode
    photos = sorted(BRIGHTON.glob('*.JPG'))[:3]
    for p in photos:
        (tmp_path / p.name).symlink_to(p)
    cam = CameraNode({'source': str(tmp_path), 'rate': 0.0, 'autostart': False, **overrides}, context=rclpy_context)
    listener, got = _listener(rclpy_context)
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(cam)
    ex.add_node(listener)
    try:
        assert _spin_until(ex, lambda: cam.pub_fix.get_subscription_count() > 0)
        while cam.publish_next():
            ex.spin_once(timeout_sec=0.01)
        assert _spin_until(ex, lambda: len(got['fix']) == len(photos))
    finally:
        ex.shutdown()
        listener.destroy_node()
        cam.destroy_node()
    live = [msgs.fix_from_navsatfix(m)['h_m'] for m in got['fix']]
    offline = [exif_position(p, *reading)[2] for p in photos]   # the photos' EXIF times follow their names
    assert np.allclose(live, offline, atol=1e-6), (live, offline)
    if reading[0] == 'msl':   # Duluth: EGM2008 about 28.4 m below the ellipsoid
        assert np.allclose(np.array(live) - [read_exif_gps(p).alt_msl_m for p in photos], -28.4, atol=0.3)


def test_camera_node_refuses_a_relative_reading_without_a_takeoff_height(rclpy_context, tmp_path):
    from photogram_ros.nodes.camera_node import CameraNode
    shutil.copy(BRIGHTON / 'DJI_0018.JPG', tmp_path)
    with pytest.raises(ConfigError, match='take-off point need its height'):
        CameraNode({'source': str(tmp_path), 'autostart': False, 'exif_altitude': 'relative'},
                   context=rclpy_context)


def test_replay_takes_triangulates_exif_altitude_options(capsys):
    from photogram_ros import cli
    from photogram_ros.commands.common_args import exif_altitude_overrides

    def options(command):
        with pytest.raises(SystemExit):
            cli.main([command, '--help'])
        text = ' '.join(capsys.readouterr().out.split())
        text = text[text.index('options:'):]

        def block(flag):
            start = text.index(flag + ' ')
            return text[start:text.index(' --', start + 2)]
        return [block(f) for f in ('--exif-altitude', '--takeoff-altitude-m', '--takeoff-heights')]
    tri, rep = options('triangulate'), options('replay')
    assert tri[0].split(' Not given')[0] == rep[0].split(' For a photo folder')[0], (tri, rep)
    assert tri[1:] == rep[1:] and 'EXIF standard' in tri[0] and 'AbsoluteAltitude' in tri[0], (tri, rep)
    parse = cli.build_parser().parse_args
    a = parse(['replay', 'photos', '--exif-altitude', 'relative', '--takeoff-altitude-m', '158.5'])
    assert exif_altitude_overrides(a) == {'exif_altitude': 'relative', 'takeoff_altitude_m': 158.5,
                                          'takeoff_heights': 'orthometric'}
    assert exif_altitude_overrides(parse(['replay', 'photos'])) == {}
    with pytest.raises(ConfigError, match='take-off point need its height'):
        exif_altitude_overrides(parse(['replay', 'photos', '--exif-altitude', 'relative']))
    assert options('run')[1:] == tri[1:]
    assert exif_altitude_overrides(parse(['run', '--exif-altitude', 'ellipsoidal'])) == {'exif_altitude': 'ellipsoidal'}
