"""Names of the result plots and exports, in a module without imports: the daemon lists them without
loading matplotlib, openpyxl or the identification (the plots are drawn in worker processes, the
exports read when asked for)."""

PLOT_NAMES: tuple[str, ...] = ("bode", "timefit", "residuals", "convergence")

# the exports of a run's results (``station.report.export.EXPORTS``) and their media types
EXPORT_MEDIA_TYPES: dict[str, str] = {
    "parameters.csv": "text/csv; charset=utf-8", "sdyn.csv": "text/csv; charset=utf-8",
    "results.xlsx": "application/vnd.openxmlformats-officedocument.spreadsheetml.sheet"}

# results stored beside a recording that no plot reads (the model-gap analysis is a table of the report):
# storing one leaves the plots as they were, so they are not drawn again
NOT_PLOTTED: frozenset[str] = frozenset({"results.discrepancy.h5"})


def plotted(version: tuple[tuple[str, int], ...]) -> tuple[tuple[str, int], ...]:
    """The part of a recording's results version (``station.recording.stored.results_version``: file
    name, modification time) that the plots are drawn from."""
    return tuple(v for v in version if v[0] not in NOT_PLOTTED)
