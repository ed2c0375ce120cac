"""The flight report: Markdown and HTML with figures, and report.json with every figure's numbers.

A report is a list of sections; each holds paragraphs, tables (lists of dicts) and figures (PNG files
written beside the report), rendered through the Jinja2 templates of io/templates (shipped as package
data; HTML autoescaped). The same numbers go to report.json, so scripts never parse the prose.
"""

from __future__ import annotations

import base64
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


@dataclass
class Section:
    title: str
    text: list = field(default_factory=list)       # paragraphs
    tables: list = field(default_factory=list)     # (caption, [dict rows])
    figures: list = field(default_factory=list)    # (caption, png path relative to the report)


def format_cell(v) -> str:
    """A table cell: floats to 4 significant digits; None, NaN and inf as '-' (no figure)."""
    if isinstance(v, (float, np.floating)):
        return f'{v:.4g}' if np.isfinite(v) else '-'
    if v is None:
        return '-'
    return str(v)


def md_table(rows: list[dict]) -> list[str]:
    if not rows:
        return ['(none)']
    cols = list(rows[0])
    out = ['| ' + ' | '.join(cols) + ' |', '|' + '---|' * len(cols)]
    out += ['| ' + ' | '.join(format_cell(r.get(c)) for c in cols) + ' |' for r in rows]
    return out


def _jsonable(o):
    if isinstance(o, dict):
        return {str(k): _jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_jsonable(v) for v in o]
    if isinstance(o, np.ndarray):
        return _jsonable(o.tolist())
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        o = o.item()
    if isinstance(o, float) and not np.isfinite(o):
        return None     # no NaN or Infinity in report.json: a figure that does not exist is null
    return o


def software_info() -> dict:
    """What made the report: photogram_ros's version, the git commit of its checkout (with '-dirty' when the
    checkout has changes; '' when installed from a package), Python, the command line and the time (UTC)."""
    import platform
    import shlex
    import subprocess
    import sys
    from datetime import datetime, timezone

    from photogram_ros import __version__
    commit = ''
    root = Path(__file__).resolve().parents[2]
    if (root / '.git').exists():
        try:
            commit = subprocess.run(['git', '-C', str(root), 'describe', '--always', '--dirty', '--abbrev=10'],
                                    capture_output=True, text=True, timeout=10).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            commit = ''
    return {'photogram_ros': __version__, 'commit': commit, 'python': platform.python_version(),
            'command': ' '.join(shlex.quote(a) for a in [Path(sys.argv[0]).name] + sys.argv[1:]) if sys.argv else '',
            'generated_utc': datetime.now(timezone.utc).strftime('%Y-%m-%d %H:%M:%S UTC')}


def software_section(info: dict) -> Section:
    return Section('Software', [f"photogram_ros {info['photogram_ros']}"
                                + (f" (commit {info['commit']})" if info['commit'] else '')
                                + f", Python {info['python']}; report made {info['generated_utc']}.",
                                f"Command: {info['command']}"])


def _environment():
    """Jinja2 templates shipped with the package (io/templates); HTML escapes every value (the text holds
    file names, photo names and messages from the flight: never trusted as markup)."""
    from jinja2 import Environment, FileSystemLoader, StrictUndefined, select_autoescape
    env = Environment(loader=FileSystemLoader(str(TEMPLATES)), autoescape=select_autoescape(['html', 'html.j2']),
                      undefined=StrictUndefined, keep_trailing_newline=True, trim_blocks=True, lstrip_blocks=True)
    env.filters['md_cell'] = lambda v: str(v).replace('|', '\\|').replace('\n', ' ')
    return env


TEMPLATES = Path(__file__).resolve().parent / 'templates'


def write_report(out_dir: str | Path, title: str, sections: list[Section], figures: dict) -> dict:
    """Write report.md, report.html (figures embedded) and report.json to `out_dir`, from the templates
    io/templates/report.{md,html}.j2, with a last section saying which software made it (also in
    report.json's 'software'); returns the paths."""
    out = Path(out_dir)
    info = software_info()
    figures.setdefault('software', info)
    ctx = []
    for s in list(sections) + [software_section(figures['software'])]:
        tables = []
        for caption, rows in s.tables:
            cols = list(rows[0]) if rows else []
            tables.append({'caption': caption, 'columns': cols,
                           'rows': [[format_cell(r.get(c)) for c in cols] for r in rows]})
        figs = [{'caption': caption, 'png': png,
                 'data': base64.b64encode((out / png).read_bytes()).decode('ascii')} for caption, png in s.figures]
        ctx.append({'title': s.title, 'text': list(s.text), 'tables': tables, 'figures': figs})
    env = _environment()
    (out / 'report.md').write_text(env.get_template('report.md.j2').render(title=title, sections=ctx))
    (out / 'report.html').write_text(env.get_template('report.html.j2').render(title=title, sections=ctx))
    (out / 'report.json').write_text(json.dumps(_jsonable(figures), indent=1))
    return {'md': out / 'report.md', 'html': out / 'report.html', 'json': out / 'report.json'}


def histogram_png(path: Path, values: np.ndarray, xlabel: str, title: str, bins: int = 50) -> Path:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6, 3.2), dpi=100)
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    if v.size:
        lo, hi = np.percentile(v, [0.5, 99.5])
        ax.hist(np.clip(v, lo, hi), bins=bins, color='#4477aa')
    ax.set_xlabel(xlabel)
    ax.set_ylabel('count')
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def trajectory_png(path: Path, ortho_tif: Path | None, tracks: dict, targets: list, title: str) -> Path:
    """Trajectories (name -> (K, 2) easting/northing) and targets over the orthomosaic, in its CRS."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(7, 6), dpi=100)
    if ortho_tif is not None and Path(ortho_tif).exists():
        import rasterio
        with rasterio.open(ortho_tif) as ds:
            step = max(1, int(max(ds.width, ds.height) / 1500))
            img = ds.read(out_shape=(ds.count, ds.height // step, ds.width // step))
            b = ds.bounds
        rgb = np.moveaxis(img[:3], 0, -1)
        ax.imshow(rgb, extent=(b.left, b.right, b.bottom, b.top))
    colours = ['#ee3377', '#33bbee', '#ffdd44', '#44aa99']
    for k, (name, xy) in enumerate(tracks.items()):
        xy = np.asarray(xy)
        if len(xy):
            ax.plot(xy[:, 0], xy[:, 1], '.-', ms=3, lw=1, color=colours[k % len(colours)], label=name)
    for name, x, y in targets:
        ax.plot(x, y, 'k^', ms=6)
        ax.annotate(name, (x, y), fontsize=7, xytext=(3, 3), textcoords='offset points')
    ax.set_aspect('equal')
    ax.ticklabel_format(useOffset=False, style='plain')
    ax.tick_params(labelsize=7)
    ax.legend(fontsize=8)
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def series_png(path: Path, x, series: dict, xlabel: str, ylabel: str, title: str) -> Path:
    """One or more y series (name -> values) against x, as lines with markers."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(7, 3.2), dpi=100)
    for name, y in series.items():
        ax.plot(np.asarray(x), np.asarray(y, float), '.-', ms=4, lw=0.8, label=name)
    ax.axhline(0.0, color='0.6', lw=0.6)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    if len(series) > 1:
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def vectors_png(path: Path, items: list, title: str) -> Path:
    """Residual vectors at points: items of (name, kind, x, y, dx, dy, dz); arrows scaled to be seen."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(7, 6), dpi=100)
    if items:
        a = np.array([it[2:7] for it in items], float)
        span = max(float(np.ptp(a[:, 0])), float(np.ptp(a[:, 1])), 1.0)
        longest = max(float(np.max(np.hypot(a[:, 2], a[:, 3]))), 1e-6)
        scale = 0.1 * span / longest
        for (name, kind, x, y, dx, dy, dz) in items:
            colour = '#cc3311' if kind == 'check' else '#0077bb'
            ax.plot(x, y, '^', color=colour, ms=6)
            ax.annotate('', (x + dx * scale, y + dy * scale), (x, y),
                        arrowprops=dict(arrowstyle='->', color=colour, lw=1.2))
            ax.annotate(f'{name} dZ {dz * 100:+.1f} cm', (x, y), fontsize=7, xytext=(4, -10),
                        textcoords='offset points')
        ax.set_title(f'{title}\nhorizontal arrow scale x{scale:.0f} (longest {longest * 100:.1f} cm); '
                     'blue GCP, red check', fontsize=9)
    ax.set_aspect('equal')
    ax.ticklabel_format(useOffset=False, style='plain')
    ax.tick_params(labelsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path
