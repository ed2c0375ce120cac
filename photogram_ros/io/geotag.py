"""PPK geotagging: a post-processed antenna track + camera events + photos -> geo.txt and a CSV.

`geotag(GeotagInput)` reads the track (io/trajectory_formats.read_trajectory: RTKLIB/Emlid .pos,
GrafNav/Inertial Explorer exports, Emlid/TBC/Leica CSV, recognised by their content; a track of
seconds of week without a week takes the events' week; or a DJI MRK's own onboard RTK positions
when no track is given), the events (io/camera_events.py), matches photos to events
(core.exposure_positions.match_photos), places each exposure (core.exposure_positions.place_exposures)
and writes:
- `geo.txt` in OpenDroneMap's layout, as io/photo_block.read_geo_txt reads it: first line `EPSG:4326`,
  then `image lon lat h yaw pitch roll h_acc v_acc` (degrees, metres above the WGS84 ellipsoid,
  per-axis horizontal and vertical 1-sigma in metres; the angles are the photo's DJI XMP gimbal angles,
  else 0 as ODM asks when unknown);
- a CSV for Pix4D / Metashape: `image,latitude,longitude,altitude,accuracy_h,accuracy_v,yaw,pitch,roll,
  quality,how,gps_week,gps_seconds` (altitude ellipsoidal).
Anything that leaves a photo without a position (no event, an event outside the track or across a
gap, a time base that does not match) is a DataError naming the line, unless `skip_unplaced`: then
those photos are left out and named in the result's problems.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from photogram_ros.core.exposure_positions import (Q_NAMES, ExposureOptions, Placement, gps_s_to_week_tow,
                                                   match_photos, place_exposures)
from photogram_ros.errors import DataError
from photogram_ros.io import camera_events as ce
from photogram_ros.io.image_source import IMAGE_SUFFIXES, read_dji_xmp, xmp_float
from photogram_ros.io.trajectory_formats import quality_counts, read_trajectory

MAX_LISTED = 12


@dataclass
class GeotagInput:
    pos: str | None               # a trajectory file of any read format (None: the MRK's own positions)
    events: str                   # Timestamp.MRK, .bin, .tlog, or 'exif'
    photos: str | None            # folder of photos (None: the events file's folder if it has any)
    out: str                      # geo.txt to write
    csv: str | None = None        # CSV to write (None: beside out, .csv)
    match: str = 'auto'           # number, order, time, auto
    match_tolerance_s: float = 1.5
    utc_offset_s: float = 0.0     # camera clock (EXIF without zone) minus UTC
    event_kind: str = 'auto'      # CAM / TRIG / CAMERA_FEEDBACK / CAMERA_TRIGGER / CAMERA_IMAGE_CAPTURED
    accept_no_fix: bool = False
    skip_unplaced: bool = False
    options: ExposureOptions = field(default_factory=ExposureOptions)


@dataclass
class GeotagResult:
    rows: list                    # [(photo name, PlacedExposure)]
    placement: Placement
    match_how: str
    problems: list                # everything named, placed or not
    notes: list
    geo_txt: Path
    csv: Path


def photos_in(folder: Path | None) -> list[Path]:
    """The photos of a folder in file-name order ([] for None)."""
    if folder is None:
        return []
    if not folder.is_dir():
        raise DataError(f'{folder} is not a folder of photos')
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())


def _listed(items: list) -> str:
    more = f'\n  ... and {len(items) - MAX_LISTED} more' if len(items) > MAX_LISTED else ''
    return '\n  ' + '\n  '.join(items[:MAX_LISTED]) + more


def geotag(a: GeotagInput, log=None) -> GeotagResult:
    """Read, match, place and write (see the module docstring)."""
    notes = []
    folder = Path(a.photos) if a.photos else None
    if folder is None and a.events != 'exif':
        guess = Path(a.events).parent
        if photos_in(guess):
            folder = guess
    photos = photos_in(folder)
    if a.photos and not photos:
        raise DataError(f'{folder} holds no photo ({", ".join(IMAGE_SUFFIXES)})')
    mrk_rows = None
    cut_seq = None                # the photo number of an MRK's cut-off last line
    if a.events == 'exif':
        if not photos:
            raise DataError('--events exif needs --photos DIR')
        events = ce.read_exif_events(photos, a.utc_offset_s)
        notes.append(f'exposure times from the EXIF of {len(photos)} photos (camera clock - UTC = {a.utc_offset_s:g} s)')
    else:
        kind = ce.event_kind(a.events)
        if kind == 'mrk':
            mrk_rows = ce.read_mrk(a.events, notes)
            cut = ce.mrk_cut_line(a.events)
            cut_seq = cut[1] if cut else None
            events = [r.event for r in mrk_rows]
        elif kind == 'dataflash':
            events = ce.read_dataflash_events(a.events, a.event_kind)
        else:
            events = ce.read_tlog_events(a.events, a.event_kind)
        notes.append(f'{len(events)} events from {a.events} ({kind})')
    if a.pos:
        track = read_trajectory(a.pos, require_fix=not a.accept_no_fix)
        if not track.week_known:
            track = track.in_week_of(float(np.median([ev.t_gps_s for ev in events])))
        track.notes.append(f'trajectory quality: {quality_counts(track)}')
    elif mrk_rows is not None:
        track = ce.mrk_track(mrk_rows, a.events)
        notes.append('positions: the MRK\'s own onboard RTK solution (no --pos given)')
    else:
        raise DataError('give the post-processed track with --pos TRACK.pos (only a DJI MRK carries positions '
                        'of its own)')
    notes += track.notes
    problems = []
    if photos and a.events != 'exif':
        from photogram_ros.io.camera_events import photo_times_gps_s
        times = photo_times_gps_s(photos, a.utc_offset_s)
        pm = match_photos(list(zip([p.name for p in photos], times)), events, a.match, a.match_tolerance_s)
        problems += pm.problems
        for name, i in pm.pairs:
            events[i].photo = name
        match_how = pm.how
        if pm.clock_offset_s is not None:
            notes.append(f'photos matched to events {pm.how}; event time - EXIF time {pm.clock_offset_s:+.2f} s '
                         '(median; the camera clock\'s offset from GPS time)')
        if not pm.pairs:
            raise DataError('no photo could be matched to an event:' + _listed(problems))
        events_used = [events[i] for _, i in sorted(pm.pairs, key=lambda p: p[1])]
    else:
        match_how = 'exif' if a.events == 'exif' else 'none (no photos: rows named after the events)'
        for ev in events:
            ev.photo = ev.photo or f'event_{ev.seq:04d}'
        events_used = events
    placement = place_exposures(track, events_used, a.options)
    problems += placement.problems
    notes += [f'placement: {placement.mode}'] + [f'antenna -> camera: {n}' for n in placement.notes]
    if a.options.event_delay_s:
        notes.append(f'every exposure placed {a.options.event_delay_s * 1000:+.1f} ms from its event mark '
                     '(--event-delay-ms)')
    cut_photo = [p for p in problems if cut_seq is not None and p.endswith(f': no event numbered {cut_seq}')]
    unplaced = [p for p in problems if 'has no photo' not in p and p not in cut_photo]
    for p in cut_photo:
        notes.append(f'{p.split(":")[0]} left out: its MRK line was cut off')
    if unplaced and not a.skip_unplaced:
        raise DataError(f'{len(unplaced)} photos or events without a position (pass --skip-unplaced to write '
                        'the others):' + _listed(unplaced))
    if not placement.placed:
        raise DataError('no exposure could be placed:' + _listed(problems))
    rows = [(pe.event.photo, pe) for pe in placement.placed]
    out = Path(a.out)
    csv = Path(a.csv) if a.csv else out.with_suffix('.csv')
    write_geo_txt(out, rows, {p.name: p for p in photos})
    write_csv(csv, rows, {p.name: p for p in photos})
    return GeotagResult(rows, placement, match_how, problems, notes, out, csv)


def _angles(pe, photo: Path | None) -> tuple[float, float, float]:
    """The camera's yaw, pitch, roll from the photo's DJI XMP gimbal angles, else 0 as ODM asks when unknown
    (a log's body attitude is not the gimballed camera's)."""
    if photo is not None:
        xmp = read_dji_xmp(photo)
        ypr = [xmp_float(xmp, k) for k in ('GimbalYawDegree', 'GimbalPitchDegree', 'GimbalRollDegree')]
        if all(v is not None for v in ypr):
            return tuple(ypr)
    return 0.0, 0.0, 0.0


def _write_lines(path: Path, lines: list) -> None:
    try:
        Path(path).write_text('\n'.join(lines) + '\n')
    except OSError as exc:
        raise DataError(f'cannot write {path}: {exc}') from exc


def write_geo_txt(path: Path, rows: list, photos: dict) -> None:
    """OpenDroneMap geo.txt: `EPSG:4326`, then `image lon lat h yaw pitch roll h_acc v_acc` per photo."""
    lines = ['EPSG:4326']
    for name, pe in rows:
        y, p, r = _angles(pe, photos.get(name))
        lines.append(f'{name} {pe.lon_deg:.10f} {pe.lat_deg:.10f} {pe.h_m:.4f} {y:.3f} {p:.3f} {r:.3f} '
                     f'{pe.h_acc_m:.4f} {pe.v_acc_m:.4f}')
    _write_lines(path, lines)


def write_csv(path: Path, rows: list, photos: dict) -> None:
    """The same positions for Pix4D / Metashape (altitude ellipsoidal)."""
    lines = ['image,latitude,longitude,altitude,accuracy_h,accuracy_v,yaw,pitch,roll,quality,how,gps_week,gps_seconds']
    for name, pe in rows:
        y, p, r = _angles(pe, photos.get(name))
        week, tow = gps_s_to_week_tow(pe.event.t_gps_s)
        lines.append(f'{name},{pe.lat_deg:.10f},{pe.lon_deg:.10f},{pe.h_m:.4f},{pe.h_acc_m:.4f},{pe.v_acc_m:.4f},'
                     f'{y:.3f},{p:.3f},{r:.3f},{Q_NAMES.get(pe.q, pe.q)},{pe.how},{week},{tow:.6f}')
    _write_lines(path, lines)
