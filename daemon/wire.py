"""Wire schema v1, the one name the project imports it by: msgpack maps <-> message objects.
Pure functions on bytes, no sockets.

The data flow is in the file names: bytes from a transport are read by daemon/decode.py
(:func:`decode`, or :func:`unpack` then :func:`decode_map`; a bundle's frames as arrays by
daemon/block.py, or, laid out as the sender's last bundle, by daemon/layout.py without msgpack),
the message types and limits are daemon/schema.py, and the answers go back to bytes through
daemon/pack.py (:func:`encode`; a bundle's answers in one msgpack pass by :func:`replies_of`).  (daemon/encode.py is the step before: a tick's fills -> fill messages.)  The full schema, with examples, is docs/PROTOCOL.md.
"""
from __future__ import annotations

from daemon.decode import decode, decode_map, frame_key, unpack
from daemon.pack import encode, error_for, fill_map, join_replies, replies_of, to_map
from daemon.schema import (
    CONTROL_COMMANDS,
    F32,
    MAX_BUNDLE,
    MAX_CHANNELS,
    MAX_CLAIM,
    MAX_MESSAGE_BYTES,
    MAX_NAME,
    MAX_SEQ,
    MAX_STREAM_ID,
    SCHEMA_VERSION,
    STATUSES,
    Bundle,
    Control,
    ControlReply,
    Drop,
    ErrorMsg,
    FillMsg,
    Frame,
    Hello,
    HelloAck,
    Message,
    Replies,
    WireError,
)

__all__ = ["CONTROL_COMMANDS", "F32", "MAX_BUNDLE", "MAX_CHANNELS", "MAX_CLAIM", "MAX_MESSAGE_BYTES", "MAX_NAME",
           "MAX_SEQ", "MAX_STREAM_ID", "SCHEMA_VERSION", "STATUSES", "Bundle", "Control", "ControlReply", "Drop",
           "ErrorMsg", "FillMsg", "Frame", "Hello", "HelloAck", "Message", "Replies", "WireError",
           "decode", "decode_map", "encode", "error_for", "fill_map", "frame_key", "join_replies", "replies_of", "to_map",
           "unpack"]
