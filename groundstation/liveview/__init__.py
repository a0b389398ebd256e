"""The live web view of a flight (``swarm-gs demo --view``, ``swarm-gs fly --view``, ``swarm-gs replay``)."""
from groundstation.liveview.server import (DEFAULT_PORT, ControlRefused, LiveView, SessionSource, ViewError,
                                           scene)

__all__ = ["DEFAULT_PORT", "ControlRefused", "LiveView", "SessionSource", "ViewError", "scene"]
