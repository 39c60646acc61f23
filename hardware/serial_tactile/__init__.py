"""The tactile array over a serial line: wire format (driver), calibration, adapter and pty emulator.

The wire format and the byte-stream pipeline are shared with the USB transport (:mod:`hardware.usb`).
"""

from hardware.serial_tactile.adapter import SerialTactileSensor, SerialTactileSettings
from hardware.serial_tactile.calibration import Calibration, CalibrationError

__all__ = ["Calibration", "CalibrationError", "SerialTactileSensor", "SerialTactileSettings"]
