"""The lab around the station: the register of transducers and reference standards, named users with
roles, the append-only audit trail, the recordings' integrity and each transducer's history.

Every function here takes the daemon's :class:`~station.lab.store.Store` (or, for writes, the
connection of one of its transactions), so that the daemon calls them through its database door
(``station.service.db``) and the command line, a report or the certificate calls them directly."""
