"""Small text helpers for what operators read (terminal, logs, events).

``micro()``: "µm" where the output can encode it (a UTF-8 terminal or pipe), else "um".
``wrap_words``: greedy word wrap for text drawn into report images.
``identity_text``: a device's identity without empty "s/n" or "fw" fields (the SMC100, for
one, reports no serial number).
"""

from __future__ import annotations

import codecs
import sys
from collections.abc import Mapping
from typing import TextIO


def micro(stream: TextIO | None = None) -> str:
    """The micrometre symbol this stream can show."""
    stream = sys.stdout if stream is None else stream
    enc = getattr(stream, "encoding", None) or "ascii"
    try:
        codecs.encode("µ", enc)
    except (UnicodeEncodeError, LookupError):
        return "um"
    return "µm"


def with_micro(text: str, stream: TextIO | None = None) -> str:
    """``text`` with " um" written as the stream can show it."""
    unit = micro(stream)
    return text if unit == "um" else text.replace(" um", f" {unit}")


def identity_text(ident: Mapping[str, object]) -> str:
    """``Vendor Model s/n X fw Y (stage Z)``, leaving out what the device did not report."""
    parts = [str(ident.get(k) or "") for k in ("vendor", "model")]
    out = " ".join(p for p in parts if p) or "?"
    if ident.get("serial"):
        out += f" s/n {ident['serial']}"
    if ident.get("firmware"):
        out += f" fw {ident['firmware']}"
    if ident.get("stage") and ident.get("stage") != ident.get("model"):
        out += f" ({ident['stage']})"
    return out


def wrap_words(text: str, width: int) -> list[str]:
    """``text`` in lines of at most ``width`` characters, broken between words (a word
    longer than ``width`` has a line of its own)."""
    lines: list[str] = []
    cur = ""
    for word in text.split():
        if cur and len(cur) + 1 + len(word) > width:
            lines.append(cur)
            cur = word
        else:
            cur = f"{cur} {word}" if cur else word
    return [*lines, cur] if cur else lines
