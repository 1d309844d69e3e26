"""The daemon's service layer: settings, the SQLite store, the run manager, the worker processes.

Nothing here knows about HTTP; ``station.api`` maps its typed errors to statuses."""
