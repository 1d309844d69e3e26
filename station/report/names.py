"""Names of the result plots and exports, in a module without imports: the daemon lists them without
loading matplotlib, openpyxl or the identification (the plots are drawn in worker processes, the
exports read when asked for)."""

PLOT_NAMES: tuple[str, ...] = ("bode", "timefit", "residuals", "convergence")

# the exports of a run's results (``station.report.export.EXPORTS``) and their media types
EXPORT_MEDIA_TYPES: dict[str, str] = {
    "parameters.csv": "text/csv; charset=utf-8", "sdyn.csv": "text/csv; charset=utf-8",
    "results.xlsx": "application/vnd.openxmlformats-officedocument.spreadsheetml.sheet"}
