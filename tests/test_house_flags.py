"""One meaning per flag in replay and triangulate (commands/common_args.py): --gcp-heights is the vertical datum of
the control file's heights, --gcp-height-check the policy, --heights the products' heights, --lever-arm-cam the
antenna in the camera frame, --gcp the control file in either format; the old spellings still parse, with a
warning naming the new one."""

from __future__ import annotations

import pytest

from conftest import ROOT


def _parse(argv):
    from photogram_ros.cli import build_parser
    return build_parser().parse_args(argv)


def test_gcp_heights_is_the_datum_in_replay_and_triangulate(capsys):
    for cmd in (['replay', 'bag'], ['triangulate', 'in', '--out', 'o']):
        a = _parse(cmd + ['--gcp-heights', 'orthometric'])
        assert a.gcp_heights == 'orthometric'
        assert _parse(cmd).gcp_heights == 'auto'
    assert capsys.readouterr().err == ''
    a = _parse(['triangulate', 'in', '--out', 'o'])
    assert a.gcp_height_check == 'checked'
    # triangulate's old policy values still work, said deprecated, and leave the datum alone.
    a = _parse(['triangulate', 'in', '--out', 'o', '--gcp-heights', 'use'])
    assert a.gcp_height_check == 'use' and a.gcp_heights == 'auto'
    assert '--gcp-heights use is deprecated: use --gcp-height-check use' in capsys.readouterr().err
    with pytest.raises(SystemExit):      # replay never had the policy values
        _parse(['replay', 'bag', '--gcp-heights', 'use'])


def test_heights_and_the_old_orthometric_switch(capsys):
    assert _parse(['replay', 'bag']).heights == 'ellipsoidal'
    assert _parse(['replay', 'bag', '--heights', 'orthometric']).heights == 'orthometric'
    assert capsys.readouterr().err == ''
    assert _parse(['replay', 'bag', '--orthometric']).heights == 'orthometric'
    assert '--orthometric is deprecated: use --heights orthometric' in capsys.readouterr().err


def test_lever_arm_cam_and_its_old_spelling(capsys):
    assert _parse(['triangulate', 'in', '--out', 'o', '--lever-arm-cam', '0,-0.05,-0.2']).lever_arm_cam == \
        '0,-0.05,-0.2'
    assert capsys.readouterr().err == ''
    assert _parse(['triangulate', 'in', '--out', 'o', '--lever-arm=0,-0.05,-0.2']).lever_arm_cam == '0,-0.05,-0.2'
    assert '--lever-arm is deprecated: use --lever-arm-cam 0,-0.05,-0.2' in capsys.readouterr().err


def test_height_datums_say_orthometric_and_take_msl(capsys):
    a = _parse(['triangulate', 'in', '--out', 'o'])
    assert a.takeoff_heights == 'orthometric' and a.exif_altitude is None
    a = _parse(['triangulate', 'in', '--out', 'o', '--exif-altitude', 'msl', '--takeoff-heights', 'msl'])
    assert a.exif_altitude == 'orthometric' and a.takeoff_heights == 'orthometric'
    err = capsys.readouterr().err
    assert '--exif-altitude msl is deprecated' in err and '--takeoff-heights msl is deprecated' in err
    from photogram_ros.commands.triangulate import _msl
    assert _msl('orthometric') == 'msl' and _msl('ellipsoidal') == 'ellipsoidal' and _msl(None) is None


def test_gcp_takes_a_targets_file_and_a_gcp_list(tmp_path):
    from photogram_ros.errors import ConfigError
    from photogram_ros.io.aerial_triangulation import TriangulateOptions, is_targets_file
    targets = ROOT / 'bags' / 'sample_flight' / 'targets.txt'
    odm = tmp_path / 'gcp_list.txt'
    odm.write_text('EPSG:32632\n465000.0 5249000.0 500.0 1200 800 IMG_0001.JPG GCP01\n')
    assert is_targets_file(targets) and not is_targets_file(odm) and not is_targets_file(tmp_path / 'none.txt')
    opt = TriangulateOptions(gcp=str(targets), control_heights='ellipsoidal')
    assert opt.targets == str(targets) and opt.gcp is None and opt.control_heights == 'ellipsoidal'
    assert TriangulateOptions(gcp=str(odm)).gcp == str(odm)
    with pytest.raises(ConfigError, match='says the datum of its heights by the CRS'):
        TriangulateOptions(gcp=str(odm), control_heights='orthometric')
    with pytest.raises(ConfigError, match='--gcp-heights'):
        TriangulateOptions(targets=str(targets), control_heights='geoid')


def test_the_body_lever_arm_definition_for_geotag_to_adopt():
    import argparse

    from photogram_ros.commands import common_args
    p = argparse.ArgumentParser()
    common_args.add_lever_arm_body(p, 'turned by each event\'s attitude')
    assert p.parse_args(['--lever-arm', '0.1,0,-0.2']).lever_arm == '0.1,0,-0.2'
    assert 'forward,right,down' in p.format_help() and p.parse_args([]).lever_arm == '0,0,0'
