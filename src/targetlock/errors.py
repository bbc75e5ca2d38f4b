"""The errors targetlock reports to a user, and the one place library exceptions are mapped to them.

Every *expected* failure (a bad setting, a missing or unreadable file, an output that cannot be
written, a port in use, no CAN interface, no motion-capture server, a drive fault) is a
:class:`TargetlockError`: its text is one line saying what failed, on which file/port/device and
what to do. The command line prints that line and exits non-zero (``-v`` adds the traceback);
anything else is a bug and keeps its traceback. :func:`as_user_error` maps exceptions of the
standard library, python-can and canopen in one place, without importing those libraries.
"""
from __future__ import annotations

import errno
import sys

__all__ = ["TargetlockError", "ConfigError", "InputFileError", "OutputError", "DeviceError", "as_user_error",
           "EXIT_CONFIG", "EXIT_IO", "EXIT_DEVICE", "EXIT_INTERRUPTED"]

EXIT_CONFIG = 2          # bad setting / option (as argparse uses for bad options)
EXIT_IO = 3              # a file could not be read or written
EXIT_DEVICE = 4          # a bus, port, server or drive failed
EXIT_INTERRUPTED = 130   # Ctrl-C (128 + SIGINT)


class TargetlockError(Exception):
    """An expected failure, explained in one line for the user."""
    exit_code = 1


class ConfigError(TargetlockError, ValueError):
    """A configuration value is missing, unknown, of the wrong type or out of range.

    ``errors`` lists every problem found (a file's problems are reported together); ``where``
    (e.g. "config file run.toml") is said once in front of them."""
    exit_code = EXIT_CONFIG

    def __init__(self, message: str = "", errors: list[str] | None = None, where: str = "") -> None:
        self.errors = list(errors) if errors else [message]
        self.where = where
        head = f"{where}: " if where else ""
        if len(self.errors) == 1:
            text = head + self.errors[0]
        else:
            text = f"{head}{len(self.errors)} problems:" + "".join(f"\n  - {e}" for e in self.errors)
        super().__init__(text)


class InputFileError(TargetlockError):
    """An input file (config, rig file, waypoint CSV, video) is missing, unreadable or not text."""
    exit_code = EXIT_IO


class OutputError(TargetlockError):
    """An output (run folder, video, plot) cannot be written, or would overwrite an earlier run."""
    exit_code = EXIT_IO


class DeviceError(TargetlockError):
    """A bus, port, server, peer process or drive failed or is not there."""
    exit_code = EXIT_DEVICE


def _os_error(exc: OSError) -> TargetlockError:
    where = f" {exc.filename}" if exc.filename else ""
    why = exc.strerror or str(exc)
    if exc.errno == errno.EADDRINUSE:
        return DeviceError(f"port already in use ({why}): another targetlock or Motive is running on it; stop it "
                           "or choose other ports in the rig file")
    if exc.errno in (errno.ENODEV, errno.ENXIO) or "No such device" in str(exc):
        return DeviceError(f"no such device{where} ({why}): check the interface name and that it is up "
                           "(`ip link show`)")
    if exc.errno == errno.EADDRNOTAVAIL:
        return DeviceError(f"network address not available on this machine ({why}): the rig file's natnet.local_ip "
                           "/ server_ip and can.bus.udp_interface_ip must be addresses of this machine's interfaces")
    if exc.errno in (errno.ECONNREFUSED, errno.ENETUNREACH, errno.EHOSTUNREACH):
        return DeviceError(f"{why}{where}: is the server / peer running and reachable?")
    if isinstance(exc, (ConnectionError, TimeoutError)):
        return DeviceError(str(exc) or f"{type(exc).__name__}: is the server / peer running and reachable?")
    if isinstance(exc, FileNotFoundError):
        return InputFileError(f"{exc.filename or exc}: no such file or folder; check the path")
    if isinstance(exc, IsADirectoryError):
        return InputFileError(f"{exc.filename or exc}: is a folder, a file is needed")
    if isinstance(exc, NotADirectoryError):
        return OutputError(f"{exc.filename or exc}: a file is in the way where a folder is needed")
    if isinstance(exc, PermissionError):
        return OutputError(f"{exc.filename or exc}: permission denied; choose a place you may read/write")
    if exc.errno in (errno.ENOSPC, errno.EROFS, errno.EDQUOT):
        return OutputError(f"cannot write{where}: {why}")
    return InputFileError(f"{why}{where}")


# (module, exception class, one-line message) of the device errors of libraries and drivers
_LIBRARY_ERRORS = (
    ("targetlock.rig.base", "DriveFault", "drives: {exc}; check the drives and the bus (details in run.log), then re-run"),
    ("targetlock.interfaces.natnet", "NatNetParseError",
     "NatNet server: {exc}; check Motive's streaming settings (NatNet 3.x or 4.x)"),
    ("can", "CanError", "CAN bus: {exc}; check the interface (`ip link show`) or the rig file's [can.bus]"),
    ("canopen.sdo.exceptions", "SdoError", "CANopen SDO: {exc}; check node ids and that the drives are powered"),
)


def as_user_error(exc: BaseException) -> TargetlockError | None:
    """The user-facing error for ``exc``, or None if it is not an expected failure (a bug)."""
    if isinstance(exc, TargetlockError):
        return exc
    if isinstance(exc, UnicodeDecodeError):
        return InputFileError(f"a file is not UTF-8 text ({exc.reason} at byte {exc.start}); save it as UTF-8")
    # Library exceptions are looked up only if the library was imported: mapping must not import
    # python-can, canopen or the rig code just to print an error.
    for module, name, hint in _LIBRARY_ERRORS:
        lib = sys.modules.get(module)
        if lib is not None and isinstance(exc, getattr(lib, name)):
            return DeviceError(hint.format(exc=exc))
    if isinstance(exc, OSError):
        return _os_error(exc)
    return None
