"""Dense matching from a map folder's final poses (io/densify.py) and the offline products around it."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import cv2
import numpy as np
import pytest

from conftest import ROOT

TIMES = (2.0, 3.8, 5.6)   # along the first line of the tiny survey: 9 m apart at 40 m, B/H 0.22


@pytest.fixture(scope='module')
def map_dir(tmp_path_factory):
    """A map folder as the map node leaves it: origin, camera and three keyframes with true poses, no tiles."""
    from helpers.sim_world import rendered, world
    from photogram_ros.core.geodesy import LocalFrame
    from photogram_ros.io.map_store import MapStore
    cfg = world('tiny')[0]
    d = tmp_path_factory.mktemp('densify') / 'map'
    store = MapStore(d, 0.08, 256)
    store.set_origin(LocalFrame(cfg.origin_lat_deg, cfg.origin_lon_deg, cfg.origin_h_m))
    store.save_camera(cfg.camera())
    for k, (_, T, img) in enumerate(rendered(TIMES)):
        store.save_keyframe_image(k + 1, cv2.imencode('.jpg', img, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes())
        store.save_keyframe_pose(k + 1, T)
    return d


def _densify(src, out, tie_points=None):
    from photogram_ros.core.fusion import FusionConfig
    from photogram_ros.core.pairs import PairCriteria
    from photogram_ros.core.stereo import StereoParams
    from photogram_ros.io.densify import densify_map
    from photogram_ros.params import from_dict
    stereo = from_dict(StereoParams, {'downscale': 0.5})
    return densify_map(src, out, stereo, PairCriteria(), FusionConfig(), tie_points_map=tie_points)


def test_densify_searches_the_tie_points_depths_when_given(map_dir, tmp_path):
    # Without tie points (the map folder holds none) every pair searches the ground +- relief; with the
    # true ground as tie points the same pairs search only its depths, and the cloud is as good.
    from helpers.sim_world import world
    from photogram_ros.io.export import open_map
    from photogram_ros.io.map_store import MapStore
    cfg, _, terrain, _, _ = world('tiny')
    plain = _densify(MapStore(map_dir), tmp_path / 'plain')
    x, y = np.meshgrid(np.linspace(-25, 25, 60), np.linspace(-10, 50, 60))
    ties = np.column_stack([x.ravel(), y.ravel(), terrain.height_at(x.ravel(), y.ravel())])
    tied = _densify(map_dir, tmp_path / 'tied', ties)
    assert plain.pairs_done >= 2 and tied.pairs_done == plain.pairs_done
    assert plain.pairs_depth_from_tie_points == 0 and tied.pairs_depth_from_tie_points == tied.pairs_done
    for res in (plain, tied):
        assert isinstance(res.store, MapStore) and res.store.root == res.map_dir and res.store.tile_keys()
        p = open_map(res.store)[1].points()
        dz = np.abs(p['z'] - terrain.height_at(p['x'], p['y']))
        print(f'{res.pairs_done} pairs, {p["x"].size} cells, median |dz| {np.median(dz) / cfg.gsd_m:.2f} GSD')
        assert np.median(dz) <= 2 * cfg.gsd_m


OFFLINE = textwrap.dedent('''
    import collections, json, sys
    from photogram_ros.io import map_store
    opened = collections.Counter()
    init = map_store.MapStore.__init__
    def counting(self, root, *a, **k):
        opened[str(root)] += 1
        init(self, root, *a, **k)
    map_store.MapStore.__init__ = counting
    from photogram_ros.cli import main
    from photogram_ros.commands.products import densify_with_params, export_products
    map_dir, out, params = sys.argv[1:4]
    got = {}
    d = densify_with_params(map_dir, out + '/again', params, progress=False)
    got['densify'], got['pairs'] = dict(opened), d.pairs_done
    opened.clear()
    res = export_products(map_dir, out + '/products', params, min_pairs=1)
    got['products'], got['files'] = dict(opened), sorted(res['files'])
    got['from'] = res['figures']['run']['products_from']
    opened.clear()
    got['rc'] = main(['export', map_dir, '--crs', 'EPSG:32632', '--out', out + '/cmd', '--densify', '--params',
                      params, '--min-pairs', '1'])
    got['command'], got['rclpy'] = dict(opened), 'rclpy' in sys.modules
    print(json.dumps(got))
''')


def test_offline_products_load_no_ros_and_open_the_map_once(map_dir, tmp_path):
    # densify, the products of replay/run and the export command, in a process of their own: no ROS
    # module is loaded, and each opens the flight's map folder once.
    params = tmp_path / 'params.yaml'
    params.write_text('stereo_node:\n  ros__parameters:\n    downscale: 0.5\n    settle_keyframes: 10\n'
                      'map_node:\n  ros__parameters:\n    cell_m: 0.08\n    flush_interval_s: 1.0\n')
    out = tmp_path / 'out'
    r = subprocess.run([sys.executable, '-c', OFFLINE, str(map_dir), str(out), str(params)],
                       cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout.strip().splitlines()[-1])
    print(got)
    assert got['rclpy'] is False and got['rc'] == 0
    assert got['pairs'] >= 2 and got['from'].startswith('final adjustment')
    assert {'las', 'dsm', 'ortho'} <= set(got['files'])
    assert (out / 'cmd' / 'map_final').is_dir() and (out / 'cmd' / 'dsm.tif').exists()
    for phase in ('densify', 'products', 'command'):
        assert got[phase][str(map_dir)] == 1, phase


def test_offline_products_reject_a_mistyped_core_parameter(map_dir, tmp_path):
    from photogram_ros.commands.products import densify_with_params
    from photogram_ros.errors import ConfigError
    params = tmp_path / 'params.yaml'
    params.write_text('stereo_node:\n  ros__parameters:\n    relief_m: -3.0\n')
    with pytest.raises(ConfigError, match='relief_m'):
        densify_with_params(map_dir, tmp_path / 'out', str(params), progress=False)


def test_one_pair_that_cannot_be_rectified_costs_one_pair(map_dir, tmp_path, monkeypatch):
    # A pair whose cameras cannot be rectified ("rotated too far apart") used to abort the whole final
    # matching, and the products fell back to the in-flight map. Now it is skipped, counted and named.
    from photogram_ros.errors import DataError
    from photogram_ros.io import densify
    plain = _densify(map_dir, tmp_path / 'plain')
    real, calls = densify.stereo_pair, []

    def first_fails(*args, **kwargs):
        calls.append(1)
        if len(calls) == 1:
            raise DataError('stereo pair cameras are rotated too far apart to rectify (> ~85 degrees)')
        return real(*args, **kwargs)

    monkeypatch.setattr(densify, 'stereo_pair', first_fails)
    res = _densify(map_dir, tmp_path / 'one_bad')
    assert plain.pairs_done >= 2 and res.pairs_done == plain.pairs_done - 1
    assert res.pairs_skipped.get('failed') == 1 and len(res.pairs_failed) == 1
    assert 'rotated too far apart' in res.pairs_failed[0] and res.pairs_failed[0].split(':')[0].count('/') == 1
    assert res.points_fused > 0 and res.store.tile_keys()


def test_lengths_left_to_the_gsd_are_derived_from_the_keyframes(map_dir, tmp_path):
    # The tiny survey flies the simulator's camera at 40 m: the derived settings are the shipped ones.
    from photogram_ros.core import gsd
    from photogram_ros.core.fusion import FusionConfig
    from photogram_ros.core.pairs import PairCriteria
    from photogram_ros.core.stereo import StereoParams
    from photogram_ros.io.densify import densify_map
    from photogram_ros.params import from_dict
    stereo, crit, fusion = (from_dict(cls, {}) for cls in (StereoParams, PairCriteria, FusionConfig))
    assert gsd.unresolved(stereo) and gsd.unresolved(crit) and gsd.unresolved(fusion)   # the defaults
    res = densify_map(map_dir, tmp_path / 'auto', stereo, crit, fusion)
    assert res.gsd['downscale'] == 0.5 and res.gsd['cell_m'] == 0.12 and res.gsd['relief_m'] == 25.0
    assert set(res.derived) == {'downscale', 'fill_holes_m', 'edge_step_m', 'relief_m', 'depth_margin_m', 'cell_m',
                                'min_tolerance_m'}
    assert res.store.cell_m == 0.12 and res.pairs_done >= 2
    assert 30.0 < res.gsd['flying_height_m'] < 50.0


def test_the_final_matching_takes_its_own_partners_and_check(map_dir, tmp_path, monkeypatch):
    # Three keyframes on one line: one partner along it (the default) gives two pairs with the
    # left-right check; final_pairs_along 2 adds the pair of the first and third (B/H 0.44, half the
    # image in common), final_lr_check false drops the check, and two pairs confirm more cells.
    from photogram_ros.core.fusion import FusionConfig
    from photogram_ros.core.pairs import PairCriteria
    from photogram_ros.core.stereo import StereoParams
    from photogram_ros.io import densify
    from photogram_ros.io.export import open_map
    from photogram_ros.params import from_dict
    lr = []
    real = densify.stereo_pair

    def spy(cam, img_a, T_a, img_b, T_b, params, depth_range_m):
        lr.append(params.lr_check)
        return real(cam, img_a, T_a, img_b, T_b, params, depth_range_m)

    monkeypatch.setattr(densify, 'stereo_pair', spy)
    stereo = from_dict(StereoParams, {'downscale': 0.5})
    old = densify.densify_map(map_dir, tmp_path / 'old', stereo, PairCriteria(), FusionConfig())
    lr_old, lr[:] = list(lr), []
    more = PairCriteria(final_pairs_along=2, final_lr_check=False)
    new = densify.densify_map(map_dir, tmp_path / 'new', stereo, more, FusionConfig())
    assert (old.pairs_done, new.pairs_done) == (2, 3)
    assert lr_old == [True, True] and lr == [False, False, False]
    confirmed = [int((open_map(r.store)[1].points()['n_pairs'] >= 2).sum()) for r in (old, new)]
    print(f'cells two pairs confirm: {confirmed}')
    assert confirmed[1] >= 1.2 * confirmed[0]


def test_final_criteria_replace_the_partners_and_overlap():
    from photogram_ros.core.pairs import PairCriteria
    c = PairCriteria(max_pairs_along=1, max_pairs_across=0, min_overlap=0.5, final_pairs_along=3,
                     final_pairs_across=2, final_min_overlap=0.2).for_final()
    assert (c.max_pairs_along, c.max_pairs_across, c.min_overlap) == (3, 2, 0.2)


def test_products_that_cannot_be_made_still_write_a_failed_report(map_dir, tmp_path, monkeypatch):
    """No cell seen by min_pairs stereo pairs, and the cells fewer pairs saw not used (one_pair_beyond_m at
    ONE_PAIR_NEVER_M; by default they would make the products where no confirmed cell is near): no products,
    but the report is written and its verdict says why (not 'mapped' with no DSM)."""
    from photogram_ros.commands.products import export_products
    from photogram_ros.io import export
    from photogram_ros.io.export_raster import ONE_PAIR_NEVER_M, DsmParams
    monkeypatch.setattr(export, 'DsmParams', lambda: DsmParams(one_pair_beyond_m=ONE_PAIR_NEVER_M))
    res = export_products(map_dir, tmp_path / 'out', None, min_pairs=99, run={'counts': {}})
    assert res['files'] == {} and any('no products' in n and 'measured by 99 stereo pairs' in n for n in res['notes'])
    rep = json.loads((tmp_path / 'out' / 'report.json').read_text())
    assert rep['mapping']['mapped'] is False
    assert any('no products were made' in f and 'measured by 99 stereo pairs' in f for f in rep['mapping']['failures'])


def test_a_map_that_fused_nothing_searches_around_its_tie_points_ground(tmp_path):
    """A replay whose stereo found no partner in flight (or shed every pair) leaves a map folder without fused
    cells. The matching after landing then takes the ground from the adjuster's tie points (kept by the map
    stage: io/flight_inputs.save_tie_point_ground), not a height assumed 40 m under the keyframes: flown at 100 m,
    the assumed ground's depth search misses it and no pair matches; with the tie points' ground they do."""
    from photogram_ros.core.geodesy import LocalFrame
    from photogram_ros.core.rotations import make_T
    from photogram_ros.io import flight_inputs
    from photogram_ros.io.densify import GROUND_ASSUMED, GROUND_FROM_TIE_POINTS
    from photogram_ros.io.map_store import MapStore
    from photogram_ros.sim.render import Exposure, Renderer
    from photogram_ros.sim.scenario import build_world, preset
    cfg = preset('tiny', altitude_m=100.0)
    rng = np.random.default_rng(cfg.seed)
    flight, terrain, _ = build_world(cfg, rng)
    render = Renderer(terrain, cfg.camera())
    src = tmp_path / 'map'
    store = MapStore(src, 0.12, 256)
    store.set_origin(LocalFrame(cfg.origin_lat_deg, cfg.origin_lon_deg, cfg.origin_h_m))
    store.save_camera(cfg.camera())
    heights = []
    for k, t in enumerate((2.0, 3.4, 4.8)):   # 7 m apart at 100 m
        st = flight.state(t)
        T = make_T(st.map_R_cam, st.pos_enu)
        heights.append(T[2, 3] - float(terrain.height_at(np.array([T[0, 3]]), np.array([T[1, 3]]))[0]))
        img = render.render(T, Exposure(), rng)
        store.save_keyframe_image(k + 1, cv2.imencode('.jpg', img, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes())
        store.save_keyframe_pose(k + 1, T)
    assert min(heights) > 90.0
    assumed = _densify(MapStore(src), tmp_path / 'assumed')
    assert assumed.ground_from == GROUND_ASSUMED and assumed.pairs_done == 0 and assumed.points_fused == 0
    x, y = np.meshgrid(np.linspace(-25, 25, 30), np.linspace(-10, 50, 30))
    flight_inputs.save_tie_point_ground(src, float(np.median(terrain.height_at(x.ravel(), y.ravel()))), 900)
    tied = _densify(MapStore(src), tmp_path / 'tied')
    assert tied.ground_from == GROUND_FROM_TIE_POINTS and tied.pairs_done >= 1 and tied.points_fused > 10000
    assert tied.gsd['flying_height_m'] == pytest.approx(np.median(heights), abs=3.0)
    assert flight_inputs.tie_point_ground(tmp_path / 'tied') == flight_inputs.tie_point_ground(src)
