"""A stage's diagnostics (stages/report.py: levels as ints) on its node's /diagnostics."""

from __future__ import annotations

from photogram_ros.nodes.diagnostics import Diagnostics
from photogram_ros.stages.report import WARN


class StageDiagnostics:
    """Forwards count, set, rate_hz and problem to the node's Diagnostics, the level as DiagnosticStatus's."""

    def __init__(self, diag: Diagnostics):
        self.diag = diag
        self.count, self.set, self.rate_hz = diag.count, diag.set, diag.rate_hz

    def problem(self, what: str, level: int = WARN) -> None:
        self.diag.problem(what, bytes([level]))
