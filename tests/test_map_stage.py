"""The map stage (stages/map.py) without rclpy: pair clouds fused into the folder, the stream held while
nobody listens, a cloud in the wrong frame dropped with a WARN, the stream stamped with the newest cloud's
stamp while there is no clock, and the map reloaded from disk."""

import numpy as np
import pytest
from helpers.clouds import pair_cloud

from photogram_ros.core.fusion import Fusion, FusionConfig
from photogram_ros.io.map_store import MapStore
from photogram_ros.params import from_dict
from photogram_ros.stages.map import STREAM_DTYPE, MapOutputs, MapParams, MapStage
from photogram_ros.stages.report import WARN, DiagnosticsLog


def surface(x, y):
    return 3.0 + 0.05 * x - 0.02 * y


class Recorded(MapOutputs):
    def __init__(self):
        self.streams = []

    def stream(self, points, stamp_ns):
        self.streams.append((points, stamp_ns))


def test_map_stage_fuses_streams_and_persists(tmp_path):
    p = from_dict(MapParams, {'map_dir': str(tmp_path / 'map'), 'cell_m': 0.08, 'stream_max_points': 3000,
                              'use_origin_params': True, 'origin_lat_deg': 47.3977, 'origin_lon_deg': 8.5456,
                              'origin_h_m': 488.0})
    stage = MapStage(p, DiagnosticsLog(), Recorded())
    rng = np.random.default_rng(1)
    clouds = [pair_cloud(rng, surface, 10.0 * k, 0.0, 8.0, 6.0, 150.0, 0.02) for k in range(3)]
    for k, c in enumerate(clouds):
        stage.add_cloud('map', 1000 + k, c)
    stage.add_cloud('camera_optical', 2000, clouds[0])
    counts = stage.diag.counts()
    assert counts['clouds'] == 3 and counts['clouds_dropped'] == 1
    assert stage.diag.problems == [(WARN, "dense cloud dropped: dense cloud in frame 'camera_optical'; the map "
                                          'fuses clouds in "map"')]
    stage.stream(listening=False)
    assert not stage.out.streams                         # kept for when a ground station listens
    while stage._stream_pending:
        stage.stream(listening=True)
    pts = np.concatenate([s for s, _ in stage.out.streams])
    assert pts.dtype == STREAM_DTYPE and {t for _, t in stage.out.streams} == {1002}
    assert all(s.size <= 3000 for s, _ in stage.out.streams)
    assert pts.size < sum(c.size for c in clouds) / 10   # downsampled
    assert np.abs(pts['z'] - surface(pts['x'], pts['y'])).max() < 0.1
    fused = stage.fusion.points()
    stage.close()
    on_disk = Fusion(FusionConfig(0.08, 256), MapStore(tmp_path / 'map')).points()
    assert on_disk['x'].size == fused['x'].size > 10000
    stage.update_diag()
    assert stage.diag.values['cell_m'] == 0.08 and stage.diag.values['tiles_on_disk'] >= 1
    assert MapStore(tmp_path / 'map').origin.lat_deg == pytest.approx(47.3977)


def test_the_final_adjustments_camera_replaces_the_input_calibration(tmp_path):
    """camera.json holds the camera_info calibration until the bundle adjuster's full adjustment sends the camera
    its poses were adjusted with; a camera_info after that does not put the input back; densify and the report
    read it from the folder."""
    from photogram_ros.core.camera import PinholeCamera
    from photogram_ros.io.map_store import CAMERA_FINAL, CAMERA_INPUT
    p = from_dict(MapParams, {'map_dir': str(tmp_path / 'map'), 'cell_m': 0.08})
    stage = MapStage(p, DiagnosticsLog(), Recorded())
    exif = PinholeCamera(4000, 2250, 2900.0, 2900.0, 2000.0, 1125.0)
    refined = PinholeCamera(4000, 2250, 2893.5, 2893.5, 2000.0, 1125.0, (-0.011, 0.02, 0.0, 0.0, 0.0))
    stage.set_camera(exif)
    store = MapStore(tmp_path / 'map')
    assert store.load_camera() == exif and store.camera_name() == CAMERA_INPUT
    stage.set_final_camera(lambda: refined)
    stage.set_camera(exif)
    assert store.load_camera() == refined and store.camera_name() == CAMERA_FINAL and stage.camera == refined
    stage.close()


def test_keyframe_fixes_that_came_before_the_georeference_still_place_the_coverage(tmp_path):
    """The first keyframes' fixes reach the map before the block is georeferenced (no origin yet), and those
    keyframes are oriented only later: their fixes are kept and place them on the track (stand-ins), instead
    of leaving a hole in the coverage that reads as a gap."""
    from photogram_ros.core.geodesy import LocalFrame
    from photogram_ros.sim.scenario import preset
    stage = MapStage(from_dict(MapParams, {'map_dir': str(tmp_path / 'map'), 'cell_m': 0.1}), DiagnosticsLog(),
                     Recorded())
    stage.set_camera(preset('tiny').camera())
    origin = LocalFrame(47.3977, 8.5456, 488.0)
    poses = []
    for k in range(6):                       # a line east at 40 m, looking down, a keyframe every 8 m
        T = np.eye(4)
        T[:3, :3] = np.diag([1.0, -1.0, -1.0])
        T[:3, 3] = (8.0 * k, 0.0, 40.0)
        poses.append((1000 + k, T))
        stage.add_keyframe_fix(1000 + k, *origin.enu_to_geodetic(T[:3, 3]), 2)
    stage.set_origin(origin.lat_deg, origin.lon_deg, origin.h_m)
    ground = np.zeros(400, dtype=[('x', 'f4'), ('y', 'f4'), ('z', 'f4')])   # tie points on flat ground
    x, y = np.meshgrid(np.linspace(-20, 60, 20), np.linspace(-20, 20, 20))
    ground['x'], ground['y'] = x.ravel(), y.ravel()
    stage.add_sparse(ground)
    for stamp, T in poses[2:]:              # the first two are oriented only later
        stage.add_pose(stamp, T)
    stage.update_coverage()
    assert len(stage.coverage) == 6
    assert not stage.coverage.oriented(1000) and stage.coverage.oriented(1005)


def test_the_tie_points_ground_is_kept_for_the_matching_after_landing(tmp_path):
    """Each sparse cloud's median height goes to the map folder (io/flight_inputs.py), the latest one kept;
    a cloud of fewer than MIN_TIE_POINTS_GROUND points or one that cannot be read leaves it as it was."""
    from photogram_ros.io import flight_inputs
    from photogram_ros.stages.map import MIN_TIE_POINTS_GROUND
    stage = MapStage(from_dict(MapParams, {'map_dir': str(tmp_path / 'map'), 'cell_m': 0.1}), DiagnosticsLog(),
                     Recorded())
    root = tmp_path / 'map'
    assert flight_inputs.tie_point_ground(root) is None

    def ties(n, z):
        pts = np.zeros(n, dtype=[('x', 'f4'), ('y', 'f4'), ('z', 'f4')])
        pts['x'] = np.arange(n)
        pts['z'] = z
        return pts

    stage.add_sparse(ties(100, -31.5))
    assert flight_inputs.tie_point_ground(root) == pytest.approx(-31.5)
    stage.add_sparse(ties(100, -29.0))
    assert flight_inputs.tie_point_ground(root) == pytest.approx(-29.0)
    stage.add_sparse(ties(MIN_TIE_POINTS_GROUND - 1, 5.0))
    stage.add_sparse(np.zeros(50, dtype=[('x', 'f4')]))       # no z: said, nothing kept
    assert flight_inputs.tie_point_ground(root) == pytest.approx(-29.0)
    assert any('sparse cloud not used' in text for _, text in stage.diag.problems)
    stage.close()
