"""The renderer is consistent with the camera model: projections land where points appear."""

import cv2
import numpy as np
import pytest

from photogram_ros.core.rotations import invert_T, make_T, rot_x, rot_z, transform_points
from photogram_ros.sim.render import Exposure, Renderer
from photogram_ros.sim.scenario import preset
from photogram_ros.sim.targets import draw_marker, level_ground, marker_corners_enu
from photogram_ros.sim.terrain import Terrain, make_dem, make_texture

NADIR = np.array([[1, 0, 0], [0, -1, 0], [0, 0, -1.0]])


@pytest.fixture(scope='module')
def world():
    rng = np.random.default_rng(11)
    spots = [(-6.0, 3.0), (7.0, -4.0), (2.0, 6.0)]
    dem, buildings = make_dem(rng, -45, -35, 90, 70, 0.25, keep_clear=spots, n_buildings=3)
    z = [level_ground(dem, x, y, 1.8) for x, y in spots]
    tex = make_texture(rng, dem, buildings, 0.025)
    for k, (x, y) in enumerate(spots):
        draw_marker(tex, k, x, y, 2.0)
    cam = preset('sample').camera()
    corners = {k: marker_corners_enu(x, y, zz, 2.0) for k, ((x, y), zz) in enumerate(zip(spots, z))}
    return Renderer(Terrain(dem, tex, buildings), cam), corners


def test_ray_cast_reprojects_exactly(world):
    renderer, _ = world
    T = make_T(rot_z(0.4) @ NADIR @ rot_x(0.05), [2.0, 1.0, 40.0])
    p = renderer.ground_points(T).reshape(-1, 3)
    uv, ok = renderer.camera.project(transform_points(invert_T(T), p))
    vv, uu = np.mgrid[0:renderer.camera.height, 0:renderer.camera.width]
    err = np.hypot(uv[:, 0] - uu.ravel(), uv[:, 1] - vv.ravel())
    assert ok.all() and np.nanmax(err) < 1e-6
    # And the point lies on the terrain.
    dz = p[:, 2] - renderer.terrain.height_at(p[:, 0], p[:, 1])
    assert np.median(np.abs(dz)) < 0.01


def test_target_corners_in_rendered_images_match_projection(world):
    renderer, corners = world
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50))
    prm = det.getDetectorParameters()
    prm.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    det.setDetectorParameters(prm)
    rng = np.random.default_rng(5)
    ground = np.mean([c[0, 2] for c in corners.values()])
    errors = []
    for k in range(6):
        T = make_T(rot_z(0.7 * k) @ NADIR @ rot_x(0.03 * (k % 3 - 1)), [1.0 + 0.3 * k, 1.5 - 0.2 * k, ground + 24.0 + k])
        img = renderer.render(T, Exposure(noise_dn=1.0), rng)
        found, ids, _ = det.detectMarkers(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))
        for c, i in zip(found, [] if ids is None else ids.ravel()):
            uv, _ = renderer.camera.project(transform_points(invert_T(T), corners[int(i)]))
            errors.extend(np.hypot(*(c.reshape(4, 2) - uv).T))
    errors = np.array(errors)
    assert len(errors) >= 40
    assert np.median(errors) < 0.3
    assert np.max(errors) <= 0.5


def test_render_is_deterministic_and_textured(world):
    renderer, _ = world
    T = make_T(NADIR, [0.0, 0.0, 40.0])
    a = renderer.render(T, Exposure(), np.random.default_rng(1))
    b = renderer.render(T, Exposure(), np.random.default_rng(1))
    assert np.array_equal(a, b)
    # Texture at the pixel scale: the Laplacian has real energy everywhere, not only at edges.
    lap = np.abs(cv2.Laplacian(cv2.cvtColor(a, cv2.COLOR_BGR2GRAY), cv2.CV_32F))
    tiles = lap[:480 // 60 * 60, :640 // 80 * 80].reshape(8, 60, 8, 80).mean(axis=(1, 3))
    assert np.percentile(tiles, 10) > 2.0
