"""The daemon's service layer: settings, the run manager, the worker processes (the SQLite store is
``station.lab.store``, beside the lab's schema).

Nothing here knows about HTTP; ``station.api`` maps its typed errors to statuses."""
