"""Recorded runs on disk: the MCAP log format, its writer and its reader.

A run (a physical run of the robot, or a simulated trial of an experiment) is a
:class:`RunLog` of time-major tensors: the instants, the robot's coordinates and commands,
the camera's pose measurements, the tactile readings, the filters' prior and, optionally,
the ground truth (body states, contact slots, physical parameters). :func:`write_run`
writes it as an MCAP file with one JSON-Schema-described channel per kind of message;
:func:`read_run` reads it back exactly (float64 through JSON is lossless) and checks the
format: schema names and versions, required channels, message fields, the time grid.
The format is documented in the user guide's page on logs.
"""

from torchcontact.logs._reader import read_run
from torchcontact.logs._run_log import ContactTruth, RunLog
from torchcontact.logs._schemas import CHANNELS, FORMAT_VERSION, Channel
from torchcontact.logs._writer import write_run

__all__ = [
    "CHANNELS",
    "FORMAT_VERSION",
    "Channel",
    "ContactTruth",
    "RunLog",
    "read_run",
    "write_run",
]
