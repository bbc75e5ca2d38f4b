"""Operator console: the control loop with a web page to watch, select, engage, stop, tune and record."""
