"""minority's ground floor: messages, encodings, key expressions, zenoh sessions, MCAP logs.

Imports none of the project's other packages.
"""

from minority.protocol.errors import ProtocolError, SpecError
from minority.protocol.messages import (
           Chunk,
           Event,
           EventKind,
           Frame,
           Stats,
           Timing,
           decode_as,
           decode_message,
)
from minority.protocol.spec import Camera, DataRequest, Region, Spec, View, Window
from minority.protocol.wire import MessageKind

__all__ = ["Camera", "Chunk", "DataRequest", "Event", "EventKind", "Frame", "MessageKind",
           "ProtocolError", "Region", "Spec", "SpecError", "Stats", "Timing", "View", "Window",
           "decode_as",
           "decode_message"]
