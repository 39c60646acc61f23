"""USB devices (pyusb): the tactile array on a bulk/interrupt endpoint, a SpaceMouse as the master, and
an emulated bus behind pyusb's backend interface for the tests."""
