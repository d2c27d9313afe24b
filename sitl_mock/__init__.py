"""Mock PX4 / ArduPilot autopilot speaking MAVLink 2 (see ``python -m sitl_mock --help``)."""

from .control import ControlClient
from .faults import FaultSpec, parse_faults
from .log import FlightLog, read_log
from .server import MockAutopilot, MockConfig

__all__ = [
    "ControlClient",
    "FaultSpec",
    "FlightLog",
    "MockAutopilot",
    "MockConfig",
    "parse_faults",
    "read_log",
]
