"""Mission files: the survey area from a QGroundControl .plan or a GeoJSON file; coverage as GeoJSON; re-fly plans.

- `read_survey_area(path)`: outer rings [(lat_deg, lon_deg), ...] of the survey polygon(s): in a .plan
  the polygons of its Survey (and other complex) items, else its geofence inclusion polygons; in GeoJSON
  every Polygon / MultiPolygon (a Feature, a FeatureCollection or a bare geometry; lon, lat order).
- `survey_area_in_map(rings, origin)`: the same rings in map ENU, for core/coverage.py.
- `coverage_geojson(report, origin, extra)`: a FeatureCollection (WGS84 lon, lat) of the gaps (kind,
  area_m2, min_views) and the survey outline, the report's figures in its `properties`
  (`largest_gap_m2`: the largest hole in the map, a 'coverage' or 'not_oriented' gap).
- `refly_plan(gaps, height_m, footprint_w_m, footprint_l_m, ...)`: a QGroundControl .plan (mission
  version 2, simple waypoints at the mapping height above the take-off point, the camera triggered by
  distance) with lawnmower lines over each gap's outline, along its long side, spaced for the side
  overlap asked, extended by half a footprint at each end.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from photogram_ros.core.geodesy import LocalFrame
from photogram_ros.errors import DataError

# MAVLink commands and frames of the simple items.
MAV_CMD_NAV_WAYPOINT, MAV_CMD_NAV_TAKEOFF, MAV_CMD_NAV_RETURN_TO_LAUNCH = 16, 22, 20
MAV_CMD_DO_SET_CAM_TRIGG_DIST = 206
MAV_FRAME_MISSION, MAV_FRAME_GLOBAL_RELATIVE_ALT = 2, 3


def read_survey_area(path: str | Path) -> list[list[tuple[float, float]]]:
    p = Path(path)
    try:
        doc = json.loads(p.read_text())
    except (OSError, ValueError) as exc:
        raise DataError(f'survey area {p}: cannot read it as JSON ({exc}); give a QGroundControl .plan or GeoJSON') \
            from exc
    rings = _plan_rings(doc) if isinstance(doc, dict) and doc.get('fileType') == 'Plan' else _geojson_rings(doc)
    rings = [r for r in rings if len(r) >= 3]
    if not rings:
        raise DataError(f'survey area {p}: no polygon found (a .plan needs a Survey item or a geofence polygon, '
                        'GeoJSON a Polygon or MultiPolygon)')
    for r in rings:
        for lat, lon in r:
            if not (-90 <= lat <= 90 and -180 <= lon <= 180):
                raise DataError(f'survey area {p}: coordinate ({lat}, {lon}) is not latitude, longitude in degrees')
    return rings


def _plan_rings(doc: dict) -> list:
    rings = []
    for item in doc.get('mission', {}).get('items', []):
        if item.get('type') == 'ComplexItem' and item.get('polygon'):
            rings.append([(float(a), float(b)) for a, b in item['polygon']])
    if not rings:
        for poly in doc.get('geoFence', {}).get('polygons', []):
            if poly.get('inclusion', True) and poly.get('polygon'):
                rings.append([(float(a), float(b)) for a, b in poly['polygon']])
    return rings


def _geojson_rings(doc) -> list:
    if not isinstance(doc, dict):
        return []
    t = doc.get('type')
    if t == 'FeatureCollection':
        return [r for f in doc.get('features', []) for r in _geojson_rings(f)]
    if t == 'Feature':
        return _geojson_rings(doc.get('geometry') or {})
    if t == 'Polygon':
        return [[(float(c[1]), float(c[0])) for c in doc['coordinates'][0]]]
    if t == 'MultiPolygon':
        return [[(float(c[1]), float(c[0])) for c in poly[0]] for poly in doc['coordinates']]
    if t == 'GeometryCollection':
        return [r for g in doc.get('geometries', []) for r in _geojson_rings(g)]
    return []


def survey_area_in_map(rings, origin: LocalFrame) -> list[np.ndarray]:
    out = []
    for r in rings:
        a = np.asarray(r, float)
        out.append(np.atleast_2d(origin.geodetic_to_enu(a[:, 0], a[:, 1], np.full(len(a), origin.h_m)))[:, :2])
    return out


def _lonlat(origin: LocalFrame, xy_m: np.ndarray) -> list:
    xy = np.asarray(xy_m, float).reshape(-1, 2)
    lat, lon, _ = origin.enu_to_geodetic(np.column_stack([xy, np.zeros(len(xy))]))
    ring = [[round(float(a), 8), round(float(b), 8)] for a, b in zip(np.atleast_1d(lon), np.atleast_1d(lat))]
    return ring + ring[:1] if ring and ring[0] != ring[-1] else ring


def _finite(v):
    return None if isinstance(v, float) and not math.isfinite(v) else v


def coverage_geojson(report, origin: LocalFrame, extra: dict | None = None) -> dict:
    """A core.coverage.CoverageReport -> GeoJSON FeatureCollection in WGS84."""
    feats = []
    for k, g in enumerate(report.gaps):
        lat, lon, _ = origin.enu_to_geodetic(np.array([*g.centroid_map_m, 0.0]))
        feats.append({'type': 'Feature', 'geometry': {'type': 'Polygon', 'coordinates': [_lonlat(origin, g.polygon_map_m)]},
                      'properties': {'id': k, 'role': 'gap', 'kind': g.kind, 'area_m2': round(g.area_m2, 1),
                                     'min_views': g.min_views, 'centroid': [float(lon), float(lat)]}})
    for ring in report.survey_outline_map_m:
        feats.append({'type': 'Feature', 'geometry': {'type': 'Polygon', 'coordinates': [_lonlat(origin, ring)]},
                      'properties': {'role': 'survey_area'}})
    coverage_gaps = [g.area_m2 for g in report.gaps if g.kind == 'coverage']
    holes = [g.area_m2 for g in report.gaps if g.kind in ('coverage', 'not_oriented')]   # holes in the map
    props = {'keyframes': report.keyframes, 'lines': report.lines, 'survey_area_m2': round(report.survey_area_m2, 1),
             'passed_area_m2': round(report.passed_area_m2, 1), 'coverage_share': _finite(report.coverage_share),
             'stereo_share': _finite(report.stereo_share),
             'forward_overlap_median': _finite(report.forward_overlap_median),
             'forward_overlap_min': _finite(report.forward_overlap_min),
             'side_overlap_min': _finite(report.side_overlap_min),
             'low_forward_pairs': [[int(a), int(b), round(o, 3)] for a, b, o in report.low_forward_pairs],
             'gaps': len(report.gaps), 'gap_area_m2': round(float(sum(coverage_gaps)), 1),
             'not_oriented_area_m2': round(float(sum(holes) - sum(coverage_gaps)), 1),
             'largest_gap_m2': round(float(max(holes, default=0.0)), 1), **(extra or {})}
    return {'type': 'FeatureCollection', 'features': feats, 'properties': props}


def gap_rings(geojson: dict) -> list[list[tuple[float, float]]]:
    """The gap outlines [(lat, lon)] of a coverage_geojson document."""
    return [[(c[1], c[0]) for c in f['geometry']['coordinates'][0]] for f in geojson.get('features', [])
            if f.get('properties', {}).get('role') == 'gap']


def _item(seq: int, command: int, params: list, frame: int = MAV_FRAME_GLOBAL_RELATIVE_ALT, alt=None) -> dict:
    it = {'type': 'SimpleItem', 'autoContinue': True, 'command': command, 'doJumpId': seq, 'frame': frame,
          'params': params}
    if alt is not None:
        it.update({'Altitude': alt, 'AltitudeMode': 1, 'AMSLAltAboveTerrain': None})
    return it


def refly_plan(gaps: list, height_m: float, footprint_w_m: float, footprint_l_m: float, home: tuple,
               side_overlap: float = 0.6, forward_overlap: float = 0.8, speed_mps: float = 5.0) -> dict:
    """QGroundControl .plan re-flying `gaps` ([(lat, lon)] outlines) at height_m above the take-off point.

    footprint_w_m / footprint_l_m: the footprint across / along the flight lines; home: (lat, lon)."""
    if not (height_m > 0 and footprint_w_m > 0 and footprint_l_m > 0):
        raise DataError('a re-fly plan needs a positive flight height and footprint')
    spacing = footprint_w_m * (1.0 - side_overlap)
    trigger = footprint_l_m * (1.0 - forward_overlap)
    items, seq = [], 1
    items.append(_item(seq, MAV_CMD_NAV_TAKEOFF, [0, 0, 0, None, home[0], home[1], height_m], alt=height_m))
    for ring in gaps:
        a = np.asarray(ring, float)
        frame = LocalFrame(float(a[:, 0].mean()), float(a[:, 1].mean()), 0.0)
        xy = np.atleast_2d(frame.geodetic_to_enu(a[:, 0], a[:, 1], np.zeros(len(a))))[:, :2]
        # Lines along the gap's long axis (its principal direction), through its extent across it.
        d = xy - xy.mean(axis=0)
        _, _, vt = np.linalg.svd(d, full_matrices=False)
        u, v = vt[0], np.array([-vt[0][1], vt[0][0]])
        s_u, s_v = d @ u, d @ v
        n_lines = max(1, int(math.ceil((s_v.max() - s_v.min()) / spacing)))
        offsets = s_v.min() + (np.arange(n_lines) + 0.5) * (s_v.max() - s_v.min()) / n_lines
        ext = 0.5 * footprint_l_m
        for k, off in enumerate(offsets):
            ends = [s_u.min() - ext, s_u.max() + ext][:: 1 if k % 2 == 0 else -1]
            for j, t in enumerate(ends):
                p = xy.mean(axis=0) + t * u + off * v
                lat, lon, _ = frame.enu_to_geodetic(np.array([p[0], p[1], 0.0]))
                seq += 1
                items.append(_item(seq, MAV_CMD_NAV_WAYPOINT, [0, 0, 0, None, float(lat), float(lon), height_m],
                                   alt=height_m))
                seq += 1
                items.append(_item(seq, MAV_CMD_DO_SET_CAM_TRIGG_DIST, [trigger if j == 0 else 0, 0, 1, 0, 0, 0, 0],
                                   frame=MAV_FRAME_MISSION))
    seq += 1
    items.append(_item(seq, MAV_CMD_NAV_RETURN_TO_LAUNCH, [0, 0, 0, 0, 0, 0, 0], frame=MAV_FRAME_MISSION))
    return {'fileType': 'Plan', 'version': 1, 'groundStation': 'QGroundControl',
            'mission': {'version': 2, 'firmwareType': 0, 'vehicleType': 2, 'cruiseSpeed': speed_mps,
                        'hoverSpeed': speed_mps, 'plannedHomePosition': [home[0], home[1], 0], 'items': items},
            'geoFence': {'version': 2, 'circles': [], 'polygons': []},
            'rallyPoints': {'version': 2, 'points': []}}


def write_json(path: str | Path, doc: dict) -> Path:
    p = Path(path)
    tmp = p.with_suffix(p.suffix + '.tmp')
    tmp.write_text(json.dumps(doc, indent=1))
    tmp.replace(p)
    return p
