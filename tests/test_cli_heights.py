"""--heights means the same in `run`, `replay` and `export` (issue 47): one argument definition
(commands/common_args.add_heights), one code path (commands/products.export_products, which records it in the
report's run section and its Parameters table)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT
from photogram_ros import cli


def _option_help(capsys, command: str) -> str:
    """The --heights line of `photogram-ros COMMAND --help`, argparse's wrapping undone."""
    with pytest.raises(SystemExit):
        cli.main([command, '--help'])
    text = ' '.join(capsys.readouterr().out.split())
    start = text.index('--heights {', text.index('options:'))
    end = text.index(' --', start + 2)
    return text[start:end]


def test_run_replay_and_export_show_the_same_heights_option(capsys):
    run, replay, export = (_option_help(capsys, c) for c in ('run', 'replay', 'export'))
    assert run == replay == export, (run, replay, export)
    assert run.startswith('--heights {ellipsoidal,orthometric} heights of the products: WGS84 ellipsoidal '
                          '(default) or orthometric above the EGM2008 geoid'), run


def test_run_hands_heights_to_the_products_as_replay_does(monkeypatch, tmp_path):
    """`run` stopping: export_products gets --heights (the argument replay passes in the same place)."""
    from photogram_ros.commands import products, run
    got = {}

    def fake_export(map_dir, out, params_file, crs='', live_map=False, heights='ellipsoidal', *args, **kwargs):
        got['heights'] = heights
        return {'files': {}, 'notes': [], 'figures': {}}
    monkeypatch.setattr(products, 'export_products', fake_export)
    a = cli.build_parser().parse_args(['run', '--heights', 'orthometric', '--out', str(tmp_path / 'p')])
    assert run._export_at_stop(a, ('map',)) == 0
    assert got == {'heights': 'orthometric'}


def _dsm(path):
    import rasterio
    with rasterio.open(path) as ds:
        return ds.read(1, masked=True), ds.transform, ds.crs


@pytest.mark.slow
@pytest.mark.ros
def test_run_with_orthometric_heights_gives_products_one_geoid_undulation_below_the_ellipsoidal_ones(tmp_path):
    """brighton's first 10 photos through `run --heights orthometric`; its map (map_final) exported again with
    ellipsoidal heights: the DSMs differ by the EGM2008 undulation at the site (core/geoid, the oracle), and the
    report records the option."""
    import shutil

    from conftest import shared_data
    from photogram_ros.core import geoid
    from photogram_ros.io.map_store import MapStore
    photos = sorted(shared_data('photos', 'brighton_beach', 'images').glob('*.JPG'))[:10]
    (tmp_path / 'photos').mkdir()
    for p in photos:
        shutil.copy2(p, tmp_path / 'photos' / p.name)
    cfg = tmp_path / 'run.yaml'
    cfg.write_text(f'camera_node:\n  ros__parameters:\n    source: {tmp_path / "photos"}\n    rate: 0.0\n'
                   f'map_node:\n  ros__parameters:\n    map_dir: {tmp_path / "map"}\n')
    out = tmp_path / 'products'
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'run', '--params', str(cfg), '--nodes',
                        'camera,tracker,bundle,stereo,map', '--out', str(out), '--heights', 'orthometric'],
                       cwd=ROOT, capture_output=True, text=True, timeout=1200)
    log = r.stdout + r.stderr
    assert r.returncode == 0, log[-3000:]
    exported = json.loads((out / 'export.json').read_text())
    assert exported['heights'] == 'orthometric'
    rep = json.loads((out / 'report.json').read_text())
    assert rep['run']['heights'] == 'orthometric'
    assert {'node': 'products', 'parameter': '--heights', 'value': '"orthometric"', 'from': 'command'} in \
        rep['parameters']['rows']
    assert 'orthometric, above the EGM2008 geoid' in (out / 'report.md').read_text()
    ell = tmp_path / 'ellipsoidal'
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'export', str(out / 'map_final'), '--out',
                        str(ell), '--crs', exported['crs'], '--heights', 'ellipsoidal',
                        '--products', 'dsm'], cwd=ROOT, capture_output=True,
                       text=True, timeout=600)
    assert r.returncode == 0, (r.stdout + r.stderr)[-3000:]
    z_orth, t_orth, crs_orth = _dsm(out / 'dsm.tif')
    z_ell, t_ell, crs_ell = _dsm(ell / 'dsm.tif')
    assert t_orth == t_ell and crs_orth.to_epsg() == crs_ell.to_epsg() and z_orth.shape == z_ell.shape
    both = ~(np.ma.getmaskarray(z_orth) | np.ma.getmaskarray(z_ell))
    assert both.sum() > 1000
    dz = np.asarray(z_ell)[both] - np.asarray(z_orth)[both]
    origin = MapStore(out / 'map_final').origin
    n_m = float(geoid.undulation_m(origin.lat_deg, origin.lon_deg))
    print(f'ellipsoidal - orthometric DSM: median {np.median(dz):.3f} m, spread {np.ptp(dz):.3f} m over '
          f'{both.sum()} cells; EGM2008 undulation at the origin {n_m:.3f} m')
    assert abs(n_m) > 1.0   # the site has a geoid that a mix-up would show
    assert abs(np.median(dz) - n_m) < 0.05 and np.ptp(dz) < 0.1, (np.median(dz), np.ptp(dz), n_m)
