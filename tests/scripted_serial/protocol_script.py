"""``script://NAME`` for ``serial.serial_for_url`` (see the package docstring)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from scripted_serial import lookup


def serial_class_for_url(url: str) -> tuple[str, Callable[..., Any]]:
    port = lookup(url)

    def make(*_args: Any, **_kwargs: Any) -> Any:  # the settings are the script's business
        return port

    return url, make
