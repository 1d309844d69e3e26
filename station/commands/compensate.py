"""``station compensate design|apply``: an inverse filter from a calibration, applied to a measured
signal with an uncertainty at every sample (docs/compensation.md)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING

from station.errors import BadInputError

if TYPE_CHECKING:
    from station.compensate.design import CompensationFilter


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("compensate", help="design a dynamic compensation filter from a calibration, or apply one")
    cs = p.add_subparsers(dest="compensate_command", required=True, metavar="ACTION")

    d = cs.add_parser("design", help="least-squares FIR inverse filter with its coefficients' covariance")
    src = d.add_mutually_exclusive_group(required=True)
    src.add_argument("--recording", type=Path, help="a recording with a stored identification (Eq. 9 or Eq. 8)")
    src.add_argument("--table", type=Path,
                     help="CSV of sinusoidal calibration values: frequency_hz, magnitude, phase_deg|phase_rad "
                          "[, u_magnitude, u_phase_deg|u_phase_rad]")
    d.add_argument("--result", default=None,
                   help="the stored result to use (default: identify_fd_* then identify_oe_*)")
    d.add_argument("--mass", type=float, default=None, metavar="KG",
                   help="mass mounted on the transducer in the application (required with --recording)")
    d.add_argument("--mass-std", type=float, default=0.0, metavar="KG", help="its standard uncertainty")
    d.add_argument("--table-units", default="N:V", metavar="IN:OUT",
                   help="units of the table's measurand and signal (default N:V: magnitude in V/N)")
    d.add_argument("--sample-rate", type=float, required=True, metavar="HZ", help="the application's sample rate")
    d.add_argument("--band", type=float, nargs=2, metavar=("LO_HZ", "HI_HZ"), default=None,
                   help="band of interest (default: 0 Hz to cut-off / 1.5)")
    d.add_argument("--cutoff", type=float, default=None, metavar="HZ",
                   help="cut-off of the regularising low-pass (default 1.5 x the band's upper edge, at most 0.45 fs)")
    d.add_argument("--lowpass-order", type=int, default=4, help="order of the regularising low-pass (default 4)")
    d.add_argument("--taps", type=int, default=64, help="FIR length (default 64)")
    d.add_argument("--delay", type=int, default=None, metavar="SAMPLES",
                   help="delay in samples (default: the one of least error over the band)")
    d.add_argument("--allow-extrapolation", action="store_true",
                   help="accept a band beyond the calibrated frequency range (a finding names it)")
    d.add_argument("-o", "--output", type=Path, required=True, help="the filter as JSON")
    d.add_argument("--plot", type=Path, default=None, help="Bode plot (PNG)")
    d.add_argument("--json", action="store_true", help="print a summary as JSON")
    d.set_defaults(handler=run_design)

    a = cs.add_parser("apply", help="compensate a measured signal, with its standard uncertainty at every sample")
    a.add_argument("filter", type=Path, help="a filter from `station compensate design`")
    a.add_argument("signal", type=Path, help="the measured signal: .csv (time_s or --sample-rate), .h5/.hdf5, .npy")
    a.add_argument("--sample-rate", type=float, default=None, metavar="HZ", help="the signal's sample rate")
    a.add_argument("--dataset", default=None, help="HDF5 dataset of the signal")
    a.add_argument("--column", default=None, help="CSV column of the signal (when there are several)")
    noise = a.add_mutually_exclusive_group()
    noise.add_argument("--noise-std", type=float, default=0.0, help="standard deviation of white noise in the signal")
    noise.add_argument("--noise-autocov", type=Path, default=None,
                       help="the noise's one-sided autocovariance r[0], r[1], ... (one value a line, unit^2)")
    a.add_argument("--keep-delay", action="store_true",
                   help="keep the filter's delay in the time axis (default: removed, estimate at t - delay)")
    a.add_argument("--monte-carlo", type=int, default=0, metavar="N",
                   help="also N Monte Carlo draws (GUM-S1): their mean and standard deviation, and the largest "
                        "relative difference from the linear u")
    a.add_argument("--seed", type=int, default=0, help="seed of the Monte Carlo")
    a.add_argument("--block", type=int, default=1 << 16, help="samples per block (default 65536)")
    a.add_argument("-o", "--output", type=Path, required=True, help="the estimate: .csv or .h5")
    a.add_argument("--plot", type=Path, default=None, help="measured and compensated signal (PNG)")
    a.add_argument("--json", action="store_true", help="print a summary as JSON")
    a.set_defaults(handler=run_apply)


def _summary_text(doc: dict) -> str:
    lines = [f"FIR compensation filter: {doc['taps']} taps at {doc['sample_rate_hz']:g} Hz "
             f"({doc['unit_in']} -> {doc['unit_out']})",
             f"  delay {doc['delay_samples']} samples = {doc['delay_s'] * 1e3:.6g} ms; band {doc['band_hz'][0]:g} to "
             f"{doc['band_hz'][1]:g} Hz; cut-off {doc['cutoff_hz']:g} Hz (order {doc['lowpass_order']})",
             f"  fit RMS over the band {doc['fit_rms_band']:.3g}; dynamic error bound {doc['dynamic_error_bound']:.3g} "
             "(relative, for signals within the band); noise gain "
             f"{doc['noise_gain']:.4g} {doc['unit_out']}/{doc['unit_in']}"]
    t = doc["transducer"]
    lines.append("  transducer: " + ", ".join(f"{n} = {v:.6g} {u}" for n, v, u in
                                                zip(t["names"], t["theta"], t["units"], strict=True)))
    lines += [f"  assumption: {k}: {v}" for k, v in t["assumptions"].items()]
    lines += [f"  finding {c['severity']}: {c['name']}: {c['message']}" for c in doc["findings"]]
    return "\n".join(lines)


def run_design(args: argparse.Namespace) -> int:
    from station.compensate.design import DesignSpec, default_cutoff, design_filter
    from station.compensate.plots import bode_plot
    from station.compensate.sensor import fit_table, read_table, sensor_from_recording

    if args.recording is not None:
        if args.mass is None:
            raise BadInputError("--recording needs --mass: the mass mounted on the transducer in the application (kg)")
        sensor = sensor_from_recording(str(args.recording), args.mass, args.mass_std, args.result)
    else:
        if args.mass is not None:
            raise BadInputError("a table carries no masses: --mass applies to --recording only")
        from station.bounded import read_text_limited

        text = read_text_limited(args.table, 4 * 1024 * 1024, "calibration table", say_what=True)
        unit_in, _, unit_out = args.table_units.partition(":")
        sensor = fit_table(read_table(text), unit_in or "N", unit_out or "V", f"table {args.table.name}")
    fs = args.sample_rate
    if args.band is None and args.cutoff is None:
        raise BadInputError("state the band of interest (--band LO HI) or the cut-off (--cutoff)")
    band = tuple(args.band) if args.band is not None else (0.0, args.cutoff / 1.5)
    cutoff = args.cutoff if args.cutoff is not None else default_cutoff(band[1], fs)
    spec = DesignSpec(fs, (float(band[0]), float(band[1])), float(cutoff), args.taps, args.lowpass_order,
                      args.delay, args.allow_extrapolation)
    filt = design_filter(sensor, spec)
    doc = filt.to_dict()
    try:
        args.output.write_text(json.dumps(doc, indent=1), encoding="utf-8")
    except OSError as exc:
        raise BadInputError(f"{args.output}: cannot write the filter ({exc.strerror or exc})") from None
    if args.plot is not None:
        bode_plot(filt, args.plot)
    if args.json:
        print(json.dumps({k: v for k, v in doc.items() if k not in ("b_cov", "extra")}, indent=2))
    else:
        print(_summary_text(doc))
        print(f"  written: {args.output}" + (f", {args.plot}" if args.plot else ""))
    return 0


def load_filter(path: Path) -> CompensationFilter:
    """A filter written by ``station compensate design``; refused with one message when it is not one."""
    from station.bounded import read_text_limited
    from station.compensate.design import CompensationFilter

    text = read_text_limited(path, 64 * 1024 * 1024, "compensation filter", say_what=True)
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise BadInputError(f"{path}: not a readable filter ({exc})") from None
    if not isinstance(doc, dict):
        raise BadInputError(f"{path}: not a compensation filter")
    return CompensationFilter.from_dict(doc)


def run_apply(args: argparse.Namespace) -> int:
    import numpy as np

    from station.compensate.apply import Compensator, Noise, blocks, monte_carlo
    from station.compensate.plots import signal_plot
    from station.compensate.signals import check_rate, read_signal, write_output

    filt = load_filter(args.filter)
    if not (1 <= args.block <= 1 << 24):
        raise BadInputError(f"--block {args.block}: choose 1 to {1 << 24} samples")
    if args.noise_autocov is not None:
        try:
            noise = Noise.of(np.loadtxt(args.noise_autocov, ndmin=1, max_rows=100_000))
        except (OSError, ValueError) as exc:
            raise BadInputError(f"{args.noise_autocov}: not a list of numbers ({exc})") from None
    else:
        noise = Noise.white(args.noise_std)
    sig = read_signal(args.signal, args.sample_rate, args.dataset, args.column)
    check_rate(sig.sample_rate_hz, filt.sample_rate_hz)
    comp = Compensator(filt, noise)
    ys, us = [], []
    for blk in blocks(sig.x, args.block):
        y, u = comp.process(blk)
        ys.append(y)
        us.append(u)
    y, u = np.concatenate(ys), np.concatenate(us)
    t = sig.time_s
    t_est = t if args.keep_delay else t - filt.delay_s
    attrs: dict[str, object] = {
        "filter": args.filter.name, "signal": args.signal.name, "sample_rate_hz": sig.sample_rate_hz,
        "delay_s": filt.delay_s, "delay_removed": not args.keep_delay, "unit": filt.unit_out,
        "u": "standard uncertainty (k = 1): filter coefficients' covariance and the stated signal noise",
        "noise_autocov": list(noise.autocov[:8]), "band_hz": list(filt.spec.band_hz),
        "dynamic_error_bound": filt.dynamic_error_bound}
    summary: dict[str, object] = {"samples": int(y.size), "output": str(args.output), **attrs,
                                  "u_max": float(u.max()), "u_median": float(np.median(u))}
    if args.monte_carlo:
        mean, sd = monte_carlo(filt, sig.x, noise, args.monte_carlo, args.seed)
        rel = np.abs(sd / np.where(u > 0, u, np.nan) - 1)
        summary["monte_carlo"] = {"draws": args.monte_carlo, "seed": args.seed,
                                  "max_rel_diff_u": float(np.nanmax(rel)),
                                  "max_abs_diff_estimate_over_u": float(np.nanmax(np.abs(mean - y) / u))}
    write_output(args.output, t_est, y, u, filt.unit_out, attrs)
    if args.plot is not None:
        g0 = abs(complex(filt.sensor.response([0.0])[0]))
        signal_plot(t, sig.x, t_est, y, u, g0, filt.unit_out, args.plot)
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(f"compensated {y.size} samples at {sig.sample_rate_hz:g} Hz -> {args.output} ({filt.unit_out}); "
              f"delay {filt.delay_s * 1e3:.6g} ms {'kept' if args.keep_delay else 'removed'}; "
              f"u median {summary['u_median']:.3g}, max {summary['u_max']:.3g} {filt.unit_out}")
        if "monte_carlo" in summary:
            mc = summary["monte_carlo"]
            assert isinstance(mc, dict)
            print(f"  Monte Carlo ({mc['draws']} draws): u differs from the linear one by at most "
                  f"{100 * mc['max_rel_diff_u']:.2g} % (the Monte Carlo's own scatter of u: about "
                  f"{100 / (2 * mc['draws']) ** 0.5:.2g} % per sample)")
    return 0
