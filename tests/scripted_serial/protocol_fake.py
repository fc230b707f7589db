"""``fake://NAME``: the same handler as ``script://`` under the name the APT tests use."""

from scripted_serial.protocol_script import serial_class_for_url

__all__ = ["serial_class_for_url"]
