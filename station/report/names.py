"""Names of the result plots, in a module without imports: the daemon lists them without loading
matplotlib (the plots are drawn in worker processes)."""

PLOT_NAMES: tuple[str, ...] = ("bode", "timefit", "residuals", "convergence")
