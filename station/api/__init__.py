"""HTTP API of the station daemon (FastAPI) and the technicians' web page (``static/``)."""

from station.api.main import create_app

__all__ = ["create_app"]
