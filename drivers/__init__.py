"""Device layer of alignd: transports, protocol codecs, drivers and the simulated rig.

This package knows bytes, units and devices. It never imports ``alignd``.
"""
