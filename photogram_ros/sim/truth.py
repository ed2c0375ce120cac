"""Ground truth of a simulated flight: written beside its bag, read by tests, benchmarks and reports.

Files in the bag folder: `ground_truth.json` (origin, CRS, camera, per-frame poses, targets, GNSS
fixes as sent), `ground_truth_dem.npz` (the DEM grid in the `map` frame) and `targets.txt`, the
targets as a surveyor's control-point file (`photogram-ros replay BAG --gcp BAG/targets.txt`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.geodesy import LocalFrame
from photogram_ros.errors import DataError
from photogram_ros.sim.targets import Target
from photogram_ros.sim.terrain import Grid

TRUTH_JSON = 'ground_truth.json'
TRUTH_DEM = 'ground_truth_dem.npz'
TARGETS_FILE = 'targets.txt'


@dataclass
class FrameTruth:
    index: int
    stamp_ns: int
    map_T_cam: np.ndarray          # 4x4, optical camera to map
    antenna_enu: np.ndarray        # (3,) true antenna position
    published: bool                # False for frames the faulty-flight script dropped
    black: bool = False

    def to_dict(self) -> dict:
        return {'index': self.index, 'stamp_ns': self.stamp_ns, 'map_T_cam': self.map_T_cam.ravel().tolist(),
                'antenna_enu': self.antenna_enu.tolist(), 'published': self.published, 'black': self.black}

    @classmethod
    def from_dict(cls, d: dict) -> 'FrameTruth':
        return cls(int(d['index']), int(d['stamp_ns']), np.asarray(d['map_T_cam'], float).reshape(4, 4),
                   np.asarray(d['antenna_enu'], float), bool(d['published']), bool(d.get('black', False)))


@dataclass
class GroundTruth:
    origin: LocalFrame
    crs: str                                   # projected CRS of the products (UTM of the origin)
    camera: PinholeCamera
    frames: list[FrameTruth]
    targets: list[Target]
    dem: Grid
    gsd_m: float
    lever_arm_frd_m: np.ndarray
    fixes: list = field(default_factory=list)  # what the receiver sent (dicts)
    config: dict = field(default_factory=dict)
    geoid_model: str = ''

    def save(self, folder: str | Path) -> None:
        folder = Path(folder)
        doc = {
            'format': 'photogram_ros ground truth v1',
            'origin': self.origin.to_dict(), 'crs': self.crs, 'gsd_m': self.gsd_m,
            'geoid_model': self.geoid_model,
            'camera': self.camera.to_ros_yaml_dict('sim_camera'),
            'lever_arm_frd_m': np.asarray(self.lever_arm_frd_m).tolist(),
            'frames': [f.to_dict() for f in self.frames],
            'targets': [t.to_dict() for t in self.targets],
            'fixes': self.fixes, 'config': self.config,
            'dem_file': TRUTH_DEM,
        }
        (folder / TRUTH_JSON).write_text(json.dumps(doc, indent=1))
        np.savez_compressed(folder / TRUTH_DEM, dem=self.dem.data, x0_m=self.dem.x0_m, y0_m=self.dem.y0_m,
                            res_m=self.dem.res_m)

    @classmethod
    def load(cls, folder: str | Path) -> 'GroundTruth':
        folder = Path(folder)
        path = folder / TRUTH_JSON
        if not path.exists():
            raise DataError(f'no ground truth in {folder} (expected {TRUTH_JSON}): only simulator bags have it')
        doc = json.loads(path.read_text())
        z = np.load(folder / doc.get('dem_file', TRUTH_DEM))
        dem = Grid(z['dem'], float(z['x0_m']), float(z['y0_m']), float(z['res_m']))
        return cls(origin=LocalFrame.from_dict(doc['origin']), crs=doc['crs'],
                   camera=PinholeCamera.from_ros_yaml_dict(doc['camera']),
                   frames=[FrameTruth.from_dict(f) for f in doc['frames']],
                   targets=[Target.from_dict(t) for t in doc['targets']], dem=dem, gsd_m=float(doc['gsd_m']),
                   lever_arm_frd_m=np.asarray(doc['lever_arm_frd_m'], float), fixes=doc.get('fixes', []),
                   config=doc.get('config', {}), geoid_model=doc.get('geoid_model', ''))

    @staticmethod
    def exists(folder: str | Path) -> bool:
        return (Path(folder) / TRUTH_JSON).exists()

    def frame_by_stamp(self, stamp_ns: int, tol_ns: int = 1_000_000) -> FrameTruth | None:
        stamps = np.array([f.stamp_ns for f in self.frames])
        i = int(np.argmin(np.abs(stamps - stamp_ns)))
        return self.frames[i] if abs(int(stamps[i]) - int(stamp_ns)) <= tol_ns else None


def write_targets_file(folder: str | Path, truth: GroundTruth | None = None) -> Path:
    """The truth's targets as a control-point file (io/control_file.py) in `folder`: the truth's
    projected CRS, ellipsoidal heights, exact coordinates (the survey sigmas are left to the reader)."""
    from photogram_ros.core.control import SurveyedTarget
    from photogram_ros.io.control_file import write_control_file
    truth = truth if truth is not None else GroundTruth.load(folder)
    targets = []
    for t in truth.targets:
        lat, lon, h = truth.origin.enu_to_geodetic(t.center_enu)
        targets.append(SurveyedTarget(t.name, t.marker_id, float(lat), float(lon), float(h), t.role))
    return write_control_file(Path(folder) / TARGETS_FILE, targets, truth.crs,
                              comment=f'simulated survey: the board centres of the ArUco targets ({len(targets)})')
