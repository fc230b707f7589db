"""The simulated rig: emulated controller firmware, the shared world, the camera renderer.

Runtime code imports this package only when a config asks for the simulated rig.
"""
