"""minority's ground floor: messages, encodings, key expressions, zenoh sessions, MCAP logs.

Imports none of the project's other packages.
"""

from protocol.errors import ProtocolError, SpecError
from protocol.messages import Chunk, Event, EventKind, Frame, Stats, Timing, decode_as, decode_message
from protocol.spec import Camera, DataRequest, Region, Spec, View, Window
from protocol.wire import MessageKind

__all__ = ["Camera", "Chunk", "DataRequest", "Event", "EventKind", "Frame", "MessageKind",
           "ProtocolError", "Region", "Spec", "SpecError", "Stats", "Timing", "View", "Window",
           "decode_as",
           "decode_message"]
