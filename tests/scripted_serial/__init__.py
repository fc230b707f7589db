"""A pyserial URL handler for tests: ``script://NAME`` (or ``fake://NAME``) opens a
registered fake port.

Like pyserial's own ``loop://``: ``serial.serial_for_url`` looks the scheme up in
``serial.protocol_handler_packages``, so ``SerialTransport.open()`` runs its real code path
and gets the test's scripted port, instead of a test reaching into the transport.
"""

from __future__ import annotations

import weakref
from typing import Any

import serial

_ports: weakref.WeakValueDictionary[str, Any] = weakref.WeakValueDictionary()

if __name__ not in serial.protocol_handler_packages:
    serial.protocol_handler_packages.append(__name__)


def url_for(port: Any, name: str, scheme: str = "script") -> str:
    """Register ``port`` (a pyserial-like object) as ``scheme://name`` (replacing an earlier
    one of that name) and return the URL."""
    url = f"{scheme}://{name}"
    _ports[url] = port
    return url


def lookup(url: str) -> Any:
    try:
        return _ports[url]
    except KeyError:
        raise serial.SerialException(f"{url}: no scripted port registered") from None
