"""Run recording: what a run leaves on disk besides its config and summary (MCAP for Foxglove)."""
from .mcap_log import McapLog

__all__ = ["McapLog"]
