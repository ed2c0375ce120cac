"""Control-point files for flights: the surveyed ArUco targets, by name and marker id.

OpenDroneMap's gcp_list.txt without the pixel columns (the tracker finds the targets in the
keyframes itself):

    EPSG:32632                                  first line: the CRS of x y z
    # name  marker_id  x  y  z  [sigma_h_m  sigma_v_m]
    GCP01   0   465012.331  5249873.102  512.406
    CHK01,  5,  465040.000, 5249901.500, 511.980, 0.01, 0.02

- The CRS line is an EPSG code, a PROJ string, ``WGS84 UTM 32N`` (as ODM writes it) or ``WGS84``
  (= EPSG:4326). Geographic coordinates are x = longitude, y = latitude, as in ODM's files.
- Values are separated by whitespace or commas; ``#`` starts a comment.
- Names starting with CHK are check points (never used in the adjustment); more with `check_names`.
- Heights are above the WGS84 ellipsoid, unless the CRS is compound with EGM2008 heights (e.g.
  ``EPSG:32632+3855``) or the caller says `heights='orthometric'`: then EGM2008 (core/geoid.py)
  turns them into ellipsoidal heights. Other vertical datums are refused, not approximated: a
  national datum differs from EGM2008 by decimetres.
- The sigma columns are optional (both or neither); without them the survey is taken as 2 cm
  horizontal, 3 cm vertical.
- What spreadsheets write is read too (`read_text_lines`, `split_row`): UTF-8 with a byte-order mark
  (Excel's "CSV UTF-8"), UTF-16 (Excel's "Unicode text"), Windows-1252; ';' as the column separator
  with decimal commas (Excel in a European locale), decimal commas between blanks or tabs, quoted
  fields, the empty columns Excel pads rows with, and a header row after the CRS line. A row whose commas cannot be told apart (commas
  both between the columns and in the numbers) is refused, and the error says so.

For a folder of photos, `read_gcp_list` reads OpenDroneMap's own gcp_list.txt, where the points were
clicked in the photos: a CRS line, then one line per observation ``x y z px py image [name]``
(heights ellipsoidal; names CHK* and `check_names` are check points, as above).

Manual tie points (MTPs): points without coordinates an operator marked in several photos where
matching fails. In a gcp_list.txt they are the rows whose name starts with MTP (their x y z are not
read), or rows without coordinates, ``px py image name``; `read_tie_list` reads a file of such rows
alone (the CRS line is optional there). They are `GcpList.tie_rows`, never GCPs or check points.

`ControlInput` is the live graph's control file read once (by `replay`/`run` from --gcp, --check, --gcp-heights):
the path, check names and height datum as given, and the ControlSet read from them, handed whole to the bundle
node's adjustment stage; `as_dict`/`from_dict` carry it to a second process without reading the file again.
"""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from photogram_ros.core import geoid
from photogram_ros.core.control import ControlRow, ControlSet, SurveyedTarget, control_origin, is_check_name
from photogram_ros.core.geodesy import LocalFrame, crs_to_geodetic, geodetic_to_crs
from photogram_ros.core.incremental import ControlPoint
from photogram_ros.errors import DataError, GeodesyError

FORMAT_LINE = '# name marker_id x y z [sigma_h_m sigma_v_m]'
HEIGHTS = ('auto', 'ellipsoidal', 'orthometric')
_EGM2008_HEIGHT_EPSG = 3855


def _crs_of(text: str, where: str):
    """The CRS line -> (pyproj CRS, the text to keep)."""
    from pyproj import CRS
    from pyproj.exceptions import CRSError
    m = re.fullmatch(r'WGS84\s+UTM\s+(\d{1,2})\s*([NS])', text.strip(), re.IGNORECASE)
    if m and 1 <= int(m.group(1)) <= 60:
        text = f'EPSG:{(32600 if m.group(2).upper() == "N" else 32700) + int(m.group(1))}'
    elif text.strip().upper() in ('WGS84', 'WGS 84'):
        text = 'EPSG:4326'
    try:
        return CRS.from_user_input(text), text
    except CRSError as exc:
        raise DataError(f'{where}: {text!r} is not a coordinate reference system (write e.g. EPSG:32632, '
                        f'a PROJ string or "WGS84 UTM 32N" on the first line): {exc}') from exc


_DECIMAL_COMMA = re.compile(r'[-+]?\d+,\d+')
_THOUSANDS = re.compile(r'[-+]?\d{1,3}([.,\u00a0\u202f\' ]\d{3})+([.,]\d+)?')


def read_text_lines(path: Path, what: str) -> tuple[list[str], str]:
    """The lines of a text file whatever encoding a spreadsheet or an editor gave it, and the encoding
    found: a byte-order mark (UTF-8, UTF-16 LE/BE) is followed; UTF-16 without one is told by its zero
    bytes; otherwise UTF-8, else Windows-1252. A DataError names the encoding when none fits."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise DataError(f'cannot read the {what} {path}: {exc.strerror or exc}') from None
    for magic, kind in ((b'PK\x03\x04', 'spreadsheet (.xlsx) rather than text (a ZIP file'),
                        (b'\xd0\xcf\x11\xe0', 'Excel 97-2003 spreadsheet (.xls) rather than text ('),
                        (b'%PDF', 'PDF rather than text (')):
        if data.startswith(magic):
            raise DataError(f'{path}: the {what} is a {kind}): save it from the spreadsheet as "CSV UTF-8" or '
                            'plain text')
    if data.startswith(b'\xef\xbb\xbf'):
        enc = 'utf-8-sig'
    elif data.startswith((b'\xff\xfe', b'\xfe\xff')):
        enc = 'utf-16'
    elif len(data) >= 4 and data[1::2].count(0) > 0.4 * (len(data) // 2) and data[0::2].count(0) == 0:
        enc = 'utf-16-le'
    elif len(data) >= 4 and data[0::2].count(0) > 0.4 * (len(data) // 2) and data[1::2].count(0) == 0:
        enc = 'utf-16-be'
    else:
        enc = 'utf-8'
    try:
        text = data.decode(enc)
    except UnicodeDecodeError as exc:
        if enc != 'utf-8':
            raise DataError(f'{path}: the {what} looks like {enc.upper()} but does not decode as it ({exc.reason} '
                            f'at byte {exc.start}): save it as UTF-8 text') from None
        try:
            text, enc = data.decode('cp1252'), 'cp1252'
        except UnicodeDecodeError:
            raise DataError(f'{path}: the {what} is neither UTF-8, UTF-16 nor Windows-1252 text (byte '
                            f'{exc.start} is 0x{data[exc.start]:02x}): is it a spreadsheet (.xlsx) rather than '
                            'text? Save it as CSV UTF-8 or plain text') from None
    if '\x00' in text:
        raise DataError(f'{path}: the {what} holds zero bytes after decoding as {enc}: not a text file? Save it as '
                        'CSV UTF-8 or plain text')
    return text.lstrip('\ufeff').splitlines(), enc


def split_row(line: str, where: str, expected=(5, 7)) -> list[str]:
    """A row's values: separated by blanks, tabs or commas; by ';' when the row has any (Excel in a
    European locale), its commas then being decimal commas; decimal commas between blanks also when
    the blank-separated values count as `expected`. Quotes and the empty values of padded columns go."""
    line = line.strip()
    if ';' in line:
        values = [v.strip().strip('"\'').strip() for v in line.split(';')]
        values = [v.replace(',', '.') if _DECIMAL_COMMA.fullmatch(v) else v for v in values]
        values = [w for v in values for w in v.split()]
    else:
        blank = [v.strip('"\'') for v in line.split()]
        if len(blank) in expected and any(_DECIMAL_COMMA.fullmatch(v) for v in blank) and \
                all(_DECIMAL_COMMA.fullmatch(v) for v in blank if ',' in v):
            values = [v.replace(',', '.') for v in blank]
        else:
            values = [v.strip('"\'') for v in re.split(r'[\s,]+', line)]
    values = [v for v in values if v]
    if len(values) not in expected and ',' in line and ';' not in line and \
            re.search(r'\d,\d', line) and not re.search(r'\d\.\d', line):
        raise DataError(f'{where}: {line!r} has {len(values)} values: its commas look like decimal commas as well '
                        'as column separators; write numbers with a decimal point, or separate the columns with '
                        '";", blanks or tabs')
    return values


def _is_number(s: str) -> bool:
    try:
        float(s.replace(',', '.') if _DECIMAL_COMMA.fullmatch(s) else s)
        return True
    except ValueError:
        return False


def _number(s: str, what: str, where: str) -> float:
    if _DECIMAL_COMMA.fullmatch(s):
        s = s.replace(',', '.')
    try:
        v = float(s)
    except ValueError:
        if _THOUSANDS.fullmatch(s):
            raise DataError(f'{where}: {what} {s!r} has a thousands separator: write the number without it (as the '
                            'spreadsheet\'s "General" number format does)') from None
        raise DataError(f'{where}: {what} {s!r} is not a number') from None
    if not np.isfinite(v):
        raise DataError(f'{where}: {what} is {s!r}: a finite number is needed')
    return v


def read_control_file(path: str | Path, check_names=(), heights: str = 'auto') -> ControlSet:
    """Read a control-point file (see the module docstring) into a ControlSet in WGS84.

    heights: 'auto' (EGM2008 orthometric when the CRS is compound with EGM2008 heights, else
    ellipsoidal), 'ellipsoidal' or 'orthometric' (EGM2008, whatever the CRS says).
    """
    path = Path(path)
    if heights not in HEIGHTS:
        raise DataError(f'heights must be one of {list(HEIGHTS)}, got {heights!r}')
    raw, _ = read_text_lines(path, 'control-point file')
    lines = [(i + 1, ln.split('#', 1)[0].strip()) for i, ln in enumerate(raw)]
    # Rows a spreadsheet padded with empty columns (";;;;", ",,,") are empty rows.
    lines = [(n, ln) for n, ln in lines if ln.strip(';, \t"\'')]
    if not lines:
        raise DataError(f'{path} is empty: the first line must be a CRS (e.g. EPSG:32632), then one line per '
                        f'target: {FORMAT_LINE[2:]}')
    crs_line, crs_text = lines[0]
    crs, crs_name = _crs_of(crs_text.strip().strip('"\'').rstrip(';,\t ').strip('"\''), f'{path} line {crs_line}')
    horizontal, orthometric = crs, heights == 'orthometric'
    if crs.is_compound:
        horizontal = crs.sub_crs_list[0]
        vertical = crs.sub_crs_list[1]
        if heights != 'ellipsoidal':
            if vertical.to_epsg() != _EGM2008_HEIGHT_EPSG:
                raise DataError(f'{path} line {crs_line}: heights in {vertical.name!r} cannot be converted here '
                                f'(only the EGM2008 geoid ships with photogram_ros): give heights above the '
                                f'ellipsoid with the CRS {horizontal.name!r}, or EGM2008 heights '
                                f'(EPSG:{horizontal.to_epsg() or "XXXX"}+3855)')
            orthometric = True
    elif crs.is_vertical or len(crs.axis_info) not in (2, 3):
        raise DataError(f'{path} line {crs_line}: {crs.name!r} is not a horizontal CRS with x, y')
    geographic = horizontal.is_geographic
    rows = []
    for n, ln in lines[1:]:
        where = f'{path} line {n}'
        v = split_row(ln, where)
        if not rows and n == lines[1][0] and len(v) in (5, 7) and not any(_is_number(x) for x in v[1:5]):
            continue   # a spreadsheet's header row ("name marker_id x y z ...")
        if len(v) not in (5, 7):
            raise DataError(f'{where}: expected "{FORMAT_LINE[2:]}" (5 or 7 values), got {len(v)}: {ln!r}')
        name = v[0]
        try:
            marker = int(v[1])
        except ValueError:
            raise DataError(f'{where}: marker id {v[1]!r} of {name!r} is not a whole number (the ArUco id '
                            'painted on the board)') from None
        if marker < 0:
            raise DataError(f'{where}: marker id {marker} of {name!r} is negative')
        x, y, z = (_number(s, c, where) for s, c in zip(v[2:5], ('x', 'y', 'z')))
        sig = [None, None]
        if len(v) == 7:
            sig = [_number(s, c, where) for s, c in zip(v[5:7], ('sigma_h_m', 'sigma_v_m'))]
            if min(sig) <= 0:
                raise DataError(f'{where}: sigmas of {name!r} must be positive metres, got {v[5]} {v[6]}')
        if geographic and not (abs(y) <= 90 and abs(x) <= 360):
            raise DataError(f'{where}: {name!r} at x={x}, y={y} is not a longitude, latitude pair (geographic '
                            'files give the longitude first, as OpenDroneMap)')
        rows.append((n, name, marker, x, y, z, sig))
    if not rows:
        raise DataError(f'{path} lists no targets after its CRS line: add "{FORMAT_LINE[2:]}" lines')
    xs, ys, zs = (np.array([r[k] for r in rows]) for k in (3, 4, 5))
    try:
        lat, lon, h = crs_to_geodetic(xs, ys, zs, horizontal.to_wkt())
    except GeodesyError as exc:
        raise DataError(f'{path} line {crs_line}: {exc}') from exc
    # A projected CRS still maps swapped or mistyped coordinates somewhere on Earth: compare with
    # where the CRS is meant to be used (a few degrees of slack: UTM is used past its zone's edges).
    area = horizontal.area_of_use
    w, so, e, no = (area.west - 3, area.south - 3, area.east + 3, area.north + 3) if area else (-999, -90, 999, 90)
    for r, la, lo in zip(rows, np.atleast_1d(lat), np.atleast_1d(lon)):
        lo180 = (lo + 180.0) % 360.0 - 180.0 if np.isfinite(lo) else lo
        if not (np.isfinite(la) and np.isfinite(lo) and abs(la) <= 90 and so <= la <= no
                and (w <= lo180 <= e or w <= lo180 + 360 <= e)):
            raise DataError(f'{path} line {r[0]}: {r[1]!r} at x={r[3]}, y={r[4]} is outside {crs_name} '
                            '(wrong CRS or swapped columns?)')
    lat, lon, h = np.atleast_1d(lat), np.atleast_1d(lon), np.atleast_1d(h).astype(float)
    if orthometric:
        h = geoid.msl_to_ellipsoid_m(lat, lon, zs)
    targets = [SurveyedTarget(name, marker, float(la), float(lo), float(hh),
                              'check' if is_check_name(name) else 'gcp', sig[0], sig[1])
               for (_, name, marker, *_rest, sig), la, lo, hh in zip(rows, lat, lon, h)]
    written = {r[1]: float(z) for r, z in zip(rows, zs)}
    return ControlSet(targets, crs_name, str(path), written).with_checks(check_names)


def write_control_file(path: str | Path, control: ControlSet | list[SurveyedTarget], crs: str,
                       comment: str = '') -> Path:
    """Write targets (WGS84, ellipsoidal heights) in a projected or geographic 2D `crs`, heights
    ellipsoidal, so that read_control_file gives them back."""
    from pyproj import CRS
    targets = control.targets if isinstance(control, ControlSet) else list(control)
    c = CRS.from_user_input(crs)
    if c.is_compound or len(c.axis_info) != 2:
        raise DataError(f'write_control_file writes ellipsoidal heights: give a 2D CRS, not {c.name!r}')
    lines = [crs, f'# {comment}' if comment else None,
             '# heights above the WGS84 ellipsoid; names CHK* are check points (never used in the adjustment)',
             FORMAT_LINE]
    prec = 9 if c.is_geographic else 4
    for t in targets:
        x, y, _ = geodetic_to_crs(t.lat_deg, t.lon_deg, t.h_m, crs)
        row = f'{t.name} {t.marker_id} {float(x):.{prec}f} {float(y):.{prec}f} {t.h_m:.4f}'
        if t.sigma_h_m is not None and t.sigma_v_m is not None:
            row += f' {t.sigma_h_m:.4f} {t.sigma_v_m:.4f}'
        lines.append(row)
    path = Path(path)
    path.write_text('\n'.join(ln for ln in lines if ln is not None) + '\n')
    return path


@dataclass
class GcpList:
    """OpenDroneMap's gcp_list.txt: surveyed points and where they were clicked in the photos."""
    crs: str
    points: dict          # name -> (lat_deg, lon_deg, h_m), heights above the WGS84 ellipsoid
    roles: dict           # name -> 'gcp' or 'check'
    image_uv: dict        # image name -> {point name: (2,) distorted pixel}
    rows: list = field(default_factory=list)           # [ControlRow]: every observation line, in order
    file_heights: dict = field(default_factory=dict)   # name -> z as written (placeholders: 0, 400, ...)
    tie_rows: list = field(default_factory=list)       # [ControlRow]: the manual tie points' observations

    @property
    def tie_uv(self) -> dict:
        """{image name: {MTP name: (2,) distorted pixel}} (the first row of an MTP in a photo)."""
        return tie_uv(self.tie_rows)

    def central_origin(self) -> LocalFrame | None:
        """The map's origin for photos without positions: control_origin() of the points."""
        return control_origin([(*g, self.roles[n]) for n, g in self.points.items()])

    def in_map(self, origin: LocalFrame, sigma_enu_m) -> list[ControlPoint]:
        """Control points in the ENU frame at `origin`, all with the sigmas E, N, U (m) given."""
        sigma = np.asarray(sigma_enu_m, float)
        return [ControlPoint(name, np.asarray(origin.geodetic_to_enu(*geo), float), sigma, self.roles[name])
                for name, geo in self.points.items()]


def is_tie_name(name: str) -> bool:
    """A manual tie point's name: MTP..."""
    return name.upper().startswith('MTP')


def tie_uv(rows: list[ControlRow]) -> dict:
    """{image: {name: (2,) pixel}} of observation rows, the first row of a point in a photo."""
    out: dict = {}
    for r in rows:
        out.setdefault(r.image, {}).setdefault(r.name, np.asarray(r.uv, float))
    return out


def _tie_row(n: int, ln: list[str], where: str) -> ControlRow:
    u, v = (_number(s, c, where) for s, c in zip(ln[:2], ('px', 'py')))
    return ControlRow(n, ln[2], ln[3], np.array([u, v]))


def read_tie_list(path: str | Path) -> list[ControlRow]:
    """Manual tie points from a file in gcp_list.txt's layout without coordinates: ``px py image name``
    per observation (an optional CRS line first; full gcp_list rows are read when their name starts with
    MTP). Returns the rows; a point needs rows in two or more photos to be used."""
    path = Path(path)
    text, _ = read_text_lines(path, 'manual tie point file')
    lines = [(n + 1, ln.split('#', 1)[0].split()) for n, ln in enumerate(text)]
    lines = [(n, ln) for n, ln in lines if ln]
    rows = []
    for i, (n, ln) in enumerate(lines):
        where = f'{path} line {n}'
        if i == 0 and not _is_number(ln[0]):
            continue   # the CRS line of a gcp_list.txt
        if len(ln) == 4:
            rows.append(_tie_row(n, ln, where))
        elif len(ln) == 7 and is_tie_name(ln[6]):
            rows.append(_tie_row(n, ln[3:], where))
        else:
            raise DataError(f'{where}: {" ".join(ln)!r} is not a manual tie point row: write "px py image name" '
                            '(or a gcp_list.txt row "x y z px py image MTPname")')
    if not rows:
        raise DataError(f'{path} lists no manual tie points: one line per observation, "px py image name"')
    return rows


def read_gcp_list(path: str | Path, check_names=()) -> GcpList:
    """Read an OpenDroneMap gcp_list.txt (see the module docstring); a point clicked in several photos
    has one line per photo, and an unnamed one is named after its x_y. Rows of manual tie points (names
    MTP*, or ``px py image name`` without coordinates) go to `tie_rows`."""
    path = Path(path)
    text, _ = read_text_lines(path, 'GCP file')
    lines = [(n + 1, ln.split()) for n, ln in enumerate(text) if ln.strip() and not ln.lstrip().startswith('#')]
    if not lines:
        raise DataError(f'{path} is empty: the first line must be a CRS (e.g. EPSG:32632), then one line per '
                        'observation: x y z px py image [name]')
    _, crs = _crs_of(' '.join(lines[0][1]), f'{path} line {lines[0][0]}')
    points, image_uv, rows, heights, ties = {}, {}, [], {}, []
    for n, ln in lines[1:]:
        where = f'{path} line {n}'
        if len(ln) == 4 and not _is_number(ln[3]):
            ties.append(_tie_row(n, ln, where))
            continue
        if len(ln) == 7 and is_tie_name(ln[6]):
            ties.append(_tie_row(n, ln[3:], where))
            continue
        if len(ln) < 6:
            raise DataError(f'{where}: {" ".join(ln)!r} needs: x y z px py image [name] (or, for a manual tie '
                            'point, px py image name)')
        x, y, z, u, v = (_number(s, c, where) for s, c in zip(ln[:5], ('x', 'y', 'z', 'px', 'py')))
        name = ln[6] if len(ln) > 6 else f'{ln[0]}_{ln[1]}'
        lat, lon, h = crs_to_geodetic(x, y, z, crs)
        points[name] = (float(lat), float(lon), float(h))
        heights[name] = z
        image_uv.setdefault(ln[5], {})[name] = np.array([u, v])
        rows.append(ControlRow(n, ln[5], name, np.array([u, v])))
    roles = {name: 'check' if is_check_name(name, check_names) else 'gcp' for name in points}
    return GcpList(crs, points, roles, image_uv, rows, heights, ties)


@dataclass(frozen=True)
class ControlInput:
    """A flight's control file as given and as read (`read`, once): the adjustment stage takes `targets`; the
    tracker's target search and `run --separate` take `parameters()`, the bundle node's parameters naming the same
    file."""
    file: str                     # the file, resolved
    check_names: tuple = ()       # more check points than the CHK* names
    heights: str = 'auto'         # the vertical datum of the file's heights (read_control_file `heights`)
    targets: ControlSet | None = field(default=None, compare=False)

    @classmethod
    def read(cls, path: str | Path, check_names=(), heights: str = 'auto') -> 'ControlInput':
        """Read and check the file now (a DataError names the line)."""
        names = tuple(n for n in (s.strip() for s in check_names) if n)
        file = str(Path(path).resolve())
        return cls(file, names, heights, read_control_file(file, names, heights))

    def parameters(self) -> dict:
        """The bundle node's parameters (control_file, check_names, control_heights) naming this file."""
        return {'control_file': self.file, 'check_names': ','.join(self.check_names), 'control_heights': self.heights}

    def as_dict(self) -> dict:
        """Plain values (JSON) from which `from_dict` makes the same ControlInput, its targets included."""
        t = self.targets
        return {**self.parameters(), 'crs': t.crs, 'source': t.source, 'file_heights': t.file_heights,
                'targets': [asdict(s) for s in t.targets]}

    @classmethod
    def from_dict(cls, d: dict) -> 'ControlInput':
        targets = ControlSet([SurveyedTarget(**s) for s in d['targets']], d['crs'], d['source'], d['file_heights'])
        names = tuple(n for n in d['check_names'].split(',') if n)
        return cls(d['control_file'], names, d['control_heights'], targets)
