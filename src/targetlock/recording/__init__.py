"""Run recording in one place: the time series as CSV and everything as MCAP for Foxglove.

A :class:`~targetlock.experiments.runfolder.RunFolder` uses both: ``timeseries.csv`` through
:class:`TimeSeriesWriter`, mirrored with the run's poses, frames and logs into ``run.mcap``
(:class:`McapLog`, :class:`RunMcap`).
"""
from .mcap_log import McapLog
from .run_mcap import RunMcap
from .timeseries import TimeSeriesWriter

__all__ = ["McapLog", "RunMcap", "TimeSeriesWriter"]
