"""Sub-commands of the ``station`` console script; each module exposes ``register(subparsers)``.

A command's handler takes the parsed ``argparse.Namespace`` and returns the process exit code.
"""

COMMAND_MODULES: tuple[str, ...] = (
    "station.commands.simulate",
    "station.commands.transfer",
    "station.commands.simrig",
    "station.commands.identify",
    "station.commands.paper",
    "station.commands.calibrate",
    "station.commands.discrepancy",
    "station.commands.certificate",
    "station.commands.report",
    "station.commands.serve",
    "station.commands.ack",
    "station.commands.stop",
    "station.commands.batch",
    "station.commands.lab",
    "station.commands.history",
    "station.commands.compensate",
    "station.commands.verify",
    "station.commands.backup",
)
