"""Subcommands of the closed loop, vision and hardware (registered into :mod:`targetlock.cli`)."""
from __future__ import annotations
