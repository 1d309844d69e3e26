"""The rig process: the drive's one connection, its watchdog keeper, the stop port and the stop's
read-back in a process of their own, started and supervised by the daemon (``client.py``), spoken
to over a Unix socket of small, bounded, versioned messages (``channel.py``); ``serve.py`` is the
process itself (``python -m station.rigproc``)."""
