"""The adjustment stage's check of the block's shape on /diagnostics (stages/adjustment.py): core/block_check.py's
verdict, its reasons and figures."""

from __future__ import annotations

from photogram_ros.core.block_check import BlockCheckOptions, check_block, inputs_from_at
from photogram_ros.stages.report import ERROR, WARN


def block_check_on_diagnostics(diag, at, adjustment: dict | None = None) -> dict:
    """The block's own check of the adjuster `at` (core/incremental.py IncrementalAT) on `diag`: `verdict`
    and its reasons (a failed block an ERROR, a warning a WARN); after the final adjustment (`adjustment`
    given: its status and convergence) also `final_verdict`, which the flight's verdict reads
    (io/flight_verdict.mapping_verdict). Returns {'status', 'summary'} (the live quality carries it)."""
    # In flight the health check already watches keyframes not oriented: the verdict names them only
    # when they are a tenth of the flight; keyframes spilled to disk stay there (no thaw every 10 keyframes).
    v = check_block(inputs_from_at(at, adjustment=adjustment, thaw=False), BlockCheckOptions(min_oriented_warn=0.9))
    diag.set('verdict', v.status)
    diag.set('verdict_summary', v.summary)
    if adjustment is not None:
        diag.set('final_verdict', v.status)
        diag.set('final_verdict_summary', v.summary)
    fit = v.figures.get('gnss_fit', {})
    if 'rms_h_m' in fit:
        diag.set('block_gnss_fit_h_m', fit['rms_h_m'])
        diag.set('block_gnss_fit_v_m', fit['rms_v_m'])
    diag.set('block_nadir_share', v.figures.get('nadir', {}).get('share_within_deg', float('nan')))
    if v.status != 'ok':
        diag.problem(f'block check: {v.summary}', ERROR if v.status == 'failed' else WARN)
    return {'status': v.status, 'summary': v.summary}
