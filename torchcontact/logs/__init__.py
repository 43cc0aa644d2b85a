"""Recorded runs on disk: the MCAP log format, its writer and its reader.

A run (a physical run of the robot, or a simulated trial of an experiment) is a
:class:`RunLog` of time-major tensors: the instants, the robot's coordinates and commands,
the camera's pose measurements, the tactile readings, the filters' prior and, optionally,
the ground truth (body states, contact slots, physical parameters). :func:`write_run`
writes it as an MCAP file with one JSON-Schema-described channel per kind of message;
:func:`read_run` reads it back exactly (float64 through JSON is lossless) and checks the
format: schema names and versions, required channels, message fields, the time grid.
The format is documented in the user guide's page on recorded logs.

Each channel's messages are JSON with a JSON Schema (MCAP's well-known ``json`` message and
``jsonschema`` schema encodings) rather than raw bytes or a codegen-based encoding: every MCAP
tool reads them as they are, the schema states units and sizes, and the numbers stay exact, as
a float64 written as its shortest round-trip decimal (Python's ``repr``) reads back as the same
float64. Base64 of little-endian bytes would be as exact but opaque; zstd chunk compression
takes back most of the text's size.
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
