"""An emulated TSI on a real serial line: a pseudo-terminal pair the adapter opens like any port.

* :class:`PtyPort` is the line: the adapter opens :attr:`PtyPort.path` with pyserial; whatever the
  emulator writes at the other end arrives there, through the kernel's tty layer, as from a USB-serial
  adapter. :meth:`PtyPort.unplug` closes the device end (the adapter's reads fail as they do when a
  cable is pulled) and removes the name; :meth:`PtyPort.replug` brings up a new pair under the same name,
  as udev does with ``/dev/serial/by-id`` links.
* :class:`TactileDeviceEmulator` is the electronics: pressures in, wire-format frames of raw counts out,
  with its own frame counter, its own clock (an arbitrary epoch, so the adapter has to map it) and its
  own per-element calibration (so the adapter has to undo it). A write the line cannot take is lost and
  flagged as an overrun in the next frame, as firmware does.
* :class:`SimSensorFeed` publishes the simulated rig's sensor (:mod:`hardware.sim.sensor`) through a
  device emulator: every frame once, as it becomes readable.

Fault injection is plain: write garbage or a truncated frame with :meth:`PtyPort.write`, corrupt a
frame's bytes before writing them, send frames slower than the loop expects, unplug and replug.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import tty
from collections.abc import Callable
from pathlib import Path

import numpy as np

from hardware.interfaces import TactileSensor
from hardware.serial_tactile.calibration import Calibration
from hardware.serial_tactile.driver import FLAG_OVERRUN, encode_frame


class PtyPort:
    def __init__(self, directory: str | Path | None = None, name: str = "tsi"):
        self._own_dir = directory is None
        self._dir = Path(tempfile.mkdtemp(prefix="palpation-pty-")) if directory is None else Path(directory)
        self.path = self._dir / name
        self._master: int | None = None
        self.device_path = ""  # the /dev/pts/N the name points to while plugged
        self.dropped_bytes = 0
        self.replug()

    @property
    def plugged(self) -> bool:
        return self._master is not None

    def replug(self) -> None:
        """Plug in (again): a new pseudo-terminal pair behind the same :attr:`path`."""
        if self._master is not None:
            return
        master, slave = os.openpty()
        try:
            tty.setraw(slave)  # no line discipline between the emulator's bytes and the adapter
            self.device_path = os.ttyname(slave)
        finally:
            os.close(slave)
        os.set_blocking(master, False)  # a full line loses bytes instead of stalling the emulator
        self._master = master
        tmp = self.path.with_name(self.path.name + ".new")
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(self.device_path)
        os.replace(tmp, self.path)

    def unplug(self) -> None:
        """Pull the cable: the adapter's next read fails and the port's name disappears."""
        if self._master is None:
            return
        self.path.unlink(missing_ok=True)
        os.close(self._master)
        self._master = None

    def write(self, data: bytes) -> int:
        """Send bytes to the adapter; returns how many the line took (0 while unplugged)."""
        if self._master is None:
            self.dropped_bytes += len(data)
            return 0
        try:
            n = os.write(self._master, data)
        except BlockingIOError:
            n = 0
        self.dropped_bytes += len(data) - n
        return n

    def close(self) -> None:
        self.unplug()
        if self._own_dir:
            shutil.rmtree(self._dir, ignore_errors=True)

    def __enter__(self) -> PtyPort:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class TactileDeviceEmulator:
    """The array's electronics: frames of counts on its own clock and counter, through ``write``."""

    def __init__(self, write: Callable[[bytes], int], calibration: Calibration | None = None,
                 device_epoch_s: float = 5000.0, first_seq: int = 0):
        self._write = write
        self.calibration = calibration if calibration is not None else Calibration.uniform(100e3 / 4095, 40.0)
        self.device_epoch_s = device_epoch_s  # device clock = host clock + epoch
        self.seq = first_seq
        self.sent = 0
        self._overrun = False

    def frame_bytes(self, pressure_pa: np.ndarray, t_s: float, flags: int = 0) -> bytes:
        """Encode one frame sampled at host time ``t_s`` and advance the frame counter."""
        if self._overrun:
            flags |= FLAG_OVERRUN
            self._overrun = False
        counts = self.calibration.counts_for(pressure_pa)
        data = encode_frame(self.seq, round((t_s + self.device_epoch_s) * 1e6), counts, flags)
        self.seq += 1
        return data

    def send(self, pressure_pa: np.ndarray, t_s: float) -> bytes:
        """Sample, encode and write one frame; a frame the line does not fully take flags the next one."""
        data = self.frame_bytes(pressure_pa, t_s)
        if self._write(data) < len(data):
            self._overrun = True
        self.sent += 1
        return data

    def skip(self, frames: int = 1) -> None:
        """Frames sampled but never sent (the receiver sees a gap in the counter)."""
        self.seq += frames


class SerialSensorEmulator:
    """A TSI on a pseudo-terminal: :attr:`path` is the port to configure, :attr:`device` sends frames."""

    def __init__(self, calibration: Calibration | None = None, directory: str | Path | None = None,
                 device_epoch_s: float = 5000.0):
        self.port = PtyPort(directory)
        self.device = TactileDeviceEmulator(self.port.write, calibration, device_epoch_s)

    @property
    def path(self) -> str:
        return str(self.port.path)

    def send(self, pressure_pa: np.ndarray, t_s: float) -> bytes:
        return self.device.send(pressure_pa, t_s)

    def write(self, data: bytes) -> int:
        return self.port.write(data)

    def unplug(self) -> None:
        self.port.unplug()

    def replug(self) -> None:
        self.port.replug()

    def close(self) -> None:
        self.port.close()

    def __enter__(self) -> SerialSensorEmulator:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class SimSensorFeed:
    """Publish a (simulated) sensor's frames through a device emulator, each once, when readable.

    The sensor's pressure is already calibrated and tared; the emulator turns it back into counts with
    its own calibration, which the adapter then has to undo.
    """

    def __init__(self, sensor: TactileSensor, device: TactileDeviceEmulator):
        self.sensor = sensor
        self.device = device
        self._last_seq: int | None = None

    def pump(self, now_s: float) -> int:
        """Poll the sensor up to ``now_s`` and send its newest frame if it is new; returns frames sent."""
        self.sensor.poll(now_s)
        frame = self.sensor.latest()
        if frame is None or frame.seq == self._last_seq:
            return 0
        if self._last_seq is not None and frame.seq > self._last_seq + 1:
            self.device.skip(frame.seq - self._last_seq - 1)  # the sensor's own gaps stay gaps on the wire
        self._last_seq = frame.seq
        self.device.send(frame.pressure_pa, frame.t_s)
        return 1
