"""Settings that follow the camera: the lengths that depend on the ground sample distance (GSD).

Stereo, fusion and the DSM have lengths that only make sense relative to how finely the ground is
sampled: the fusion cell, the depth step around which disparities are dropped, how far holes are
filled, the margin around the tie points' depths, the fusion's height tolerance, the DSM's spread
and gap rules. They were tuned on the simulator's sample flight (640x480, f = 520 px, 40 m above
the ground, matched at half resolution: a GSD of 7.7 cm, a cloud spacing of 15.4 cm). A camera
that samples the ground 3.5 times more coarsely (a 1080p drone video at 166 m, matched at a
quarter) needs them 3.5 times longer: with the simulator's 12 cm cells every cell of that cloud
got at most one point, and the DSM, which wants three cells per DSM cell, was 2.8 % valid.

`derive(width_px, height_px, focal_px, flying_height_m)` gives them all (`GsdSettings`):
- the matching downscale: the resolution that keeps the matched image at the reference's pixel
  count (640 x 480 / 4 = 76,800 px), rounded up to eighths (so the SGBM cost per pair, and the
  disparities in pixels, stay those the matcher was tuned for, whatever the sensor);
- the cloud spacing = GSD / downscale, and the lengths = their reference values times the ratio
  of that spacing to the reference's, snapped to steps of 2^(1/2) so that a flying height within
  about 19 % of the reference's gives exactly the reference values (the sample's keyframes fly
  36-44 m above the median tie point);
- relief_m (the depth search around the ground): the same fraction of the flying height as the
  reference's 25 m of 40 m, snapped the same way.
A parameter set to AUTO (-1, the default of every one of them) takes the derived value (`resolve`):
stereo_pair and plan_pairs resolve from their own pair's height, the nodes and densify once per
flight (stated in the log, on /diagnostics and in the report); any other value is the user's. The
fusion cell must be known before fusing (map_node derives it at the first pair cloud).

Keyframe images travel to stereo at the resolution the map's cell needs, not the camera's
(`keyframe_reduction`): the largest power-of-two reduction (at most 8, as libjpeg decodes directly)
whose pixel is still no larger than the fusion cell (the cell is 0.78 of the cloud spacing, the
spacing GSD / downscale): 1 for the simulator's 640 x 480 (the cell is 1.56 of its pixels), 2 for
1080p, 4 for a 12-20 MP photo. Stereo then matches the reduced images at `downscale x reduction`
(`for_reduced_images`), the same matched resolution and GSD settings as from the full images.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from photogram_ros.errors import ConfigError

AUTO = -1.0     # a length parameter left at this value is derived from the GSD

# The reference: the simulator's sample flight, on which every length below was tuned.
REF_WIDTH_PX, REF_HEIGHT_PX, REF_FOCAL_PX, REF_FLYING_HEIGHT_M = 640, 480, 520.0, 40.0
REF_DOWNSCALE = 0.5
MATCH_PIXELS = REF_WIDTH_PX * REF_HEIGHT_PX * REF_DOWNSCALE ** 2
REF_SPACING_M = REF_FLYING_HEIGHT_M / REF_FOCAL_PX / REF_DOWNSCALE
# Lengths proportional to the cloud spacing (GSD / downscale), at the reference.
REF_LENGTHS_M = {
    'cell_m': 0.12,             # fusion cell (map_node): 0.78 of the cloud spacing
    'fill_holes_m': 2.0,        # stereo: unmatched gaps interpolated up to this far from matched pixels
    'edge_step_m': 1.0,         # stereo: a depth step this large drops the disparities beside it
    'depth_margin_m': 4.0,      # pairs: margin around the tie points' depths
    'min_tolerance_m': 0.3,     # fusion: smallest height disagreement that rejects a pair
    'dsm_max_spread_m': 0.5,    # DSM: a cell whose points span more is no-data (a wall)
    'dsm_fill_gaps_m': 3.0,     # DSM: gaps up to this wide between agreeing sides are interpolated
}
REF_RELIEF_M = 25.0             # depth search half-range around the ground: a fraction of the height
AUTO_NAMES = ('downscale', 'relief_m', *REF_LENGTHS_M)


def snap(ratio: float) -> float:
    """`ratio` rounded to the nearest power of sqrt(2) (1 for 0.84..1.19)."""
    if not (ratio > 0 and math.isfinite(ratio)):
        raise ConfigError(f'a GSD ratio must be positive and finite, not {ratio}')
    return 2.0 ** (round(2.0 * math.log2(ratio)) / 2.0)


def matching_downscale(width_px: int, height_px: int) -> float:
    """Scale of the rectified images that keeps about MATCH_PIXELS matched, up to eighths, in [1/8, 1]."""
    s = math.sqrt(MATCH_PIXELS / (float(width_px) * float(height_px)))
    return min(1.0, max(0.125, math.ceil(s * 8.0 - 1e-9) / 8.0))


@dataclass(frozen=True)
class GsdSettings:
    """The GSD of a camera at a flying height and the settings derived from it."""
    width_px: int
    height_px: int
    focal_px: float
    flying_height_m: float
    gsd_m: float                 # ground pixel at the full resolution, nadir
    downscale: float             # the matching resolution
    spacing_m: float             # cloud spacing: gsd_m / downscale
    scale: float                 # snapped spacing_m / REF_SPACING_M: the factor of the lengths
    height_scale: float          # snapped flying_height_m / REF_FLYING_HEIGHT_M: the factor of relief_m
    cell_m: float
    fill_holes_m: float
    edge_step_m: float
    depth_margin_m: float
    min_tolerance_m: float
    dsm_max_spread_m: float
    dsm_fill_gaps_m: float
    relief_m: float

    def as_dict(self) -> dict:
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in dataclasses.asdict(self).items()}

    def summary(self) -> str:
        return (f'GSD {self.gsd_m * 100:.1f} cm ({self.width_px}x{self.height_px}, f {self.focal_px:.0f} px, '
                f'{self.flying_height_m:.0f} m above ground), matched at {self.downscale:g} (cloud spacing '
                f'{self.spacing_m * 100:.1f} cm, lengths x{self.scale:.2f} the simulator\'s): cell '
                f'{self.cell_m:g} m, fill_holes {self.fill_holes_m:g} m, edge_step {self.edge_step_m:g} m, '
                f'depth_margin {self.depth_margin_m:g} m, relief {self.relief_m:g} m, fusion tolerance '
                f'{self.min_tolerance_m:g} m, DSM spread {self.dsm_max_spread_m:g} m / gaps {self.dsm_fill_gaps_m:g} m')


def _len(ref_m: float, factor: float) -> float:
    return float(f'{ref_m * factor:.3g}')   # 3 significant digits: the reference values come out exact


def derive(width_px: int, height_px: int, focal_px: float, flying_height_m: float,
           downscale: float = AUTO) -> GsdSettings:
    """The settings of a camera (image size, focal length in pixels) flying `flying_height_m` above the
    ground; `downscale` given (not AUTO) is the matching resolution the lengths follow."""
    if not (width_px > 0 and height_px > 0 and focal_px > 0):
        raise ConfigError(f'camera {width_px}x{height_px}, f {focal_px} px: cannot derive a GSD')
    if not (flying_height_m > 0 and math.isfinite(flying_height_m)):
        raise ConfigError(f'flying height {flying_height_m} m above the ground: cannot derive a GSD '
                          '(is the ground height right?)')
    ds = matching_downscale(width_px, height_px) if downscale == AUTO else float(downscale)
    gsd = flying_height_m / focal_px
    spacing = gsd / ds
    k = snap(spacing / REF_SPACING_M)
    kh = snap(flying_height_m / REF_FLYING_HEIGHT_M)
    lengths = {name: _len(ref, k) for name, ref in REF_LENGTHS_M.items()}
    return GsdSettings(int(width_px), int(height_px), float(focal_px), float(flying_height_m), gsd, ds, spacing,
                       k, kh, relief_m=_len(REF_RELIEF_M, kh), **lengths)


def unresolved(obj) -> list[str]:
    """The names of `obj`'s (a parameter dataclass) fields among AUTO_NAMES that are left at AUTO."""
    names = {f.name for f in dataclasses.fields(obj)}
    return [n for n in AUTO_NAMES if n in names and getattr(obj, n) == AUTO]


def resolve(obj, settings: GsdSettings):
    """A copy of the parameter dataclass `obj` with its AUTO fields set from `settings` (and the names set)."""
    names = unresolved(obj)
    if not names:
        return obj, []
    return dataclasses.replace(obj, **{n: getattr(settings, n) for n in names}), names


# The fusion cell in cloud spacings at the reference (0.78): the map's cell in matched pixels.
CELL_PER_SPACING = REF_LENGTHS_M['cell_m'] / REF_SPACING_M
MAX_KEYFRAME_REDUCTION = 8


def keyframe_reduction(width_px: int, height_px: int, downscale: float = AUTO) -> int:
    """The power-of-two reduction (1, 2, 4 or 8) of keyframe images whose pixel is no larger than the map's
    cell: the cell spans CELL_PER_SPACING / downscale full-resolution pixels (downscale AUTO: the matching
    downscale of this size). 1 at the simulator's 640 x 480, 4 at 20 MP."""
    ds = matching_downscale(width_px, height_px) if downscale == AUTO else float(downscale)
    if not 0 < ds <= 1:
        raise ConfigError(f'matching downscale {ds} must be in (0, 1]')
    cell_px = CELL_PER_SPACING / ds
    r = 1
    while 2 * r <= min(cell_px, MAX_KEYFRAME_REDUCTION) + 1e-9:
        r *= 2
    return r


def for_reduced_images(params, reduction: float):
    """A copy of the (resolved) stereo parameters for images reduced by `reduction` (full pixels per reduced
    pixel): the matching downscale relative to the reduced image, so the matched resolution is unchanged
    (the metric lengths are). The parameters as they are for a reduction of 1."""
    if reduction == 1:
        return params
    if params.downscale == AUTO:
        raise ConfigError('resolve the matching downscale (gsd.resolve) before reducing the images')
    ds = params.downscale * float(reduction)
    if not 0 < ds <= 1:
        raise ConfigError(f'keyframe images reduced {reduction}x are coarser than the matching downscale '
                          f'{params.downscale}: send them at a smaller reduction')
    return dataclasses.replace(params, downscale=ds)


def check_auto_or_at_least(obj, minima: dict) -> None:
    """ConfigError unless each named field is AUTO or at least its minimum (the fields' declared range
    starts at AUTO so that validate() lets AUTO through)."""
    for name, lo in minima.items():
        v = getattr(obj, name)
        if v != AUTO and v < lo:
            raise ConfigError(f'parameter {name!r} = {v} must be at least {lo}, or {AUTO:g} to derive it from '
                              'the GSD')


def tolerance_for_cell(cell_m: float) -> float:
    """The fusion's min_tolerance_m for cells of `cell_m`: the reference's scaled by the cell."""
    return _len(REF_LENGTHS_M['min_tolerance_m'], snap(cell_m / REF_LENGTHS_M['cell_m']))


def dsm_lengths_for_cell(cell_m: float) -> tuple[float, float]:
    """(max spread, gap fill) of a DSM over fused cells of `cell_m`: the reference's scaled by the cell."""
    k = snap(cell_m / REF_LENGTHS_M['cell_m'])
    return _len(REF_LENGTHS_M['dsm_max_spread_m'], k), _len(REF_LENGTHS_M['dsm_fill_gaps_m'], k)
