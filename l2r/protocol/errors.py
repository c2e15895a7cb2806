"""The error every check of a peer's data raises (apart, so that both the messages and the
observation spec can raise it)."""

from __future__ import annotations


class ProtocolError(ValueError):
    """A message that cannot be accepted: ``str(error)`` says why in words, ``reason`` in one
    stable identifier (such as ``out_of_range``) that receivers count rejections by."""

    def __init__(self, text: str, reason: str):
        super().__init__(text)
        self.reason = reason
